"""Tools that make data and models: excitation records, training, the Koopman baseline."""

#: exit status of ``train --bag`` whose model is written but not fit to control (no params.yaml)
NOT_FIT = 3
