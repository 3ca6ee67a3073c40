"""Tools that make data and models: excitation records, training, the Koopman baseline."""
