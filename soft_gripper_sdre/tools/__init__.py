"""The command lines (``python -m soft_gripper_sdre.tools.<wing>.<tool>``), in four wings:

* :mod:`~soft_gripper_sdre.tools.graph` — run the node graph as processes: the demo, several hands,
  two hosts, identification recordings, a foreign gripper's recipe, topic echo;
* :mod:`~soft_gripper_sdre.tools.learning` — data and models: record the simulator's excitation
  data, train the SDC model (from ``.npz`` records or bags), fit the Koopman baseline;
* :mod:`~soft_gripper_sdre.tools.judging` — how good the results are: the laws compared, robustness,
  the seed sweep, the weight sweep, the input matrix, reports and figures of a recorded run, and
  the job runner the sweeps share;
* :mod:`~soft_gripper_sdre.tools.benchmarks` — how fast: ``make bench`` and its graph, deployment
  and CPU-hog parts, one DDS hop.

``params_doc`` (the parameter reference in docs/) stays here.
"""
