# soft_gripper_sdre: the two commands of the README and their helpers.
#   make demo   - the grasp over the real node graph on the shipped defaults
#   make test   - the whole test suite (fast + slow), as CI runs it
# Both build the venv from nothing (Python 3.11, pinned requirements.txt).

PYTHON  ?= python3.11
VENV    ?= .venv
PY      := $(VENV)/bin/python
STAMP   := $(VENV)/.installed
# numba's on-disk cache of the compiled control kernels, filled once (compiling takes about a
# minute; every process started later loads them from the cache in about a second)
KERNELS := soft_gripper_sdre/control/kernels/__pycache__/kernels.stamp
OUT     ?= runs/demo

.PHONY: demo test test-fast venv kernels model model-from-bags bench sweep input-matrix lock clean two-hands two-hosts

$(STAMP): requirements.txt setup.py setup.cfg package.xml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.txt
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(STAMP)

venv: $(STAMP)

# numba's cache of the kernels, filled in two processes (the general kernels take about as long as
# the others); the import before them empties a stale cache once.
$(KERNELS): $(STAMP) $(wildcard soft_gripper_sdre/control/kernels/*.py)
	$(PY) -c 'import soft_gripper_sdre.control.kernels'
	$(PY) -c 'from soft_gripper_sdre.control.kernels import warm_up_general; warm_up_general()' & \
	general=$$!; \
	$(PY) -c 'from soft_gripper_sdre.control.kernels import warm_up_hand, warm_up_check_loop; warm_up_hand(); warm_up_check_loop()' \
	&& wait $$general
	mkdir -p $(@D) && touch $@

kernels: $(KERNELS)

demo: $(KERNELS)
	$(PY) -m soft_gripper_sdre.tools.graph.demo --out $(OUT)

# The tests mostly wait on DDS and wall clocks: those run on TEST_WORKERS pytest-xdist workers (a
# file's tests on one worker); the tests marked serial measure timing, latency or tracking against
# a bar that a neighbour's load would move, and run after them, alone. Both parts always run
# (pytest's status 5, no test selected, counts as passed).
TEST_WORKERS ?= 2
PARALLEL := -n $(TEST_WORKERS) --dist loadfile
BOTH_PASSED := for s in $$a $$b; do test $$s -eq 0 || test $$s -eq 5 || exit $$s; done

test: $(KERNELS)
	$(PY) -m pytest -v $(PARALLEL) -m "not serial"; a=$$?; \
	$(PY) -m pytest -v -m serial; b=$$?; $(BOTH_PASSED)

test-fast: $(KERNELS)
	$(PY) -m pytest $(PARALLEL) -m "not slow and not serial"; a=$$?; \
	$(PY) -m pytest -m "serial and not slow"; b=$$?; $(BOTH_PASSED)

# Reproduce the shipped models from nothing: collect the excitation data, then train the SDC
# networks and fit the Koopman baseline to the same records.
# the math kernels pinned as the shipped model was made (docs/model.md "The same model on another
# machine"; tools/procs.PINNED_KERNELS)
model: export OPENBLAS_CORETYPE = Haswell
model: export MKL_CBWR = AVX2,STRICT
model: export ATEN_CPU_CAPABILITY = avx2
model: $(STAMP)
	$(PY) -m soft_gripper_sdre.tools.learning.collect --out data/excitation
	$(PY) -m soft_gripper_sdre.tools.learning.train --data data/excitation --out runs/train --install
	$(PY) -m soft_gripper_sdre.tools.learning.koopman --data data/excitation --out runs/koopman --install

# The same model learned over the ROS interfaces, as on a robot: the excitation node plays each
# identification signal on the simulator node while the recorder records (one bag per signal),
# then train --bag learns from the bags (docs/model.md "Training from bags"; not installed).
BAGS ?= runs/bags
model-from-bags: $(STAMP)
	rm -rf $(BAGS)
	$(PY) -m soft_gripper_sdre.tools.graph.excite --out $(BAGS)/train --signals u1 u2 u3 x1 x2
	$(PY) -m soft_gripper_sdre.tools.graph.excite --out $(BAGS)/val --signals u4
	$(PY) -m soft_gripper_sdre.tools.learning.train --bag $(BAGS)/train --val-bag $(BAGS)/val --out runs/train_bags --preset default

bench: $(KERNELS) bench-train
	$(PY) -m soft_gripper_sdre.tools.benchmarks.bench --write BENCHMARKS.md

# training's stages, 5 runs per case with their spread and the load (part of bench; its rows go to
# BENCHMARKS.md through runs/bench_train.json). The hand's records are collected when missing;
# add the foreign grippers' bags (directories with train/ and val/), e.g.
# make bench-train BENCH_TRAIN_ARGS="--hand-data data/excitation --bags 'tendon3, 200 Hz=runs/t3'"
BENCH_TRAIN_ARGS ?= --hand-data data/excitation
.PHONY: bench-train
bench-train: $(KERNELS)
	test -d data/excitation || $(PY) -m soft_gripper_sdre.tools.learning.collect --out data/excitation
	$(PY) -m soft_gripper_sdre.tools.benchmarks.bench_train $(BENCH_TRAIN_ARGS) --write runs/bench_train.json

# the deployment loop alone (a driver stand-in, the estimator and the controller; part of bench):
# make bench-deploy DEPLOY_ARGS='--variants base composed shm composed+shm --rate 1000'
.PHONY: bench-deploy
DEPLOY_ARGS ?=
bench-deploy: $(KERNELS)
	$(PY) -m soft_gripper_sdre.tools.benchmarks.bench_deploy $(DEPLOY_ARGS)

# the graph in lockstep and pipelined mode beside their floors (the floor rows of bench alone):
# make bench-floor FLOOR_REPEATS=5
.PHONY: bench-floor
FLOOR_REPEATS ?= 5
bench-floor: $(KERNELS)
	$(PY) -m soft_gripper_sdre.tools.benchmarks.bench --floor $(FLOOR_REPEATS)

# docs/results.md "Noise, gains and the finger's bending modes"
sweep: $(KERNELS)
	$(PY) -m soft_gripper_sdre.tools.judging.sweep --out runs/sweep

input-matrix: $(STAMP)
	$(PY) -m soft_gripper_sdre.tools.judging.input_matrix --out runs/input_matrix

# The sweeps run their jobs on every core, or as Ray tasks on a cluster with RAY=ADDRESS
# (make evaluate RAY=auto; make ray installs the optional Ray first; tools/judging/jobs.py)
RUNNER = $(if $(RAY),--ray $(RAY))

# docs/results.md "Beyond the paper": every law on the grasp and a fast grasp, the model vs ground truth
.PHONY: evaluate
evaluate: $(KERNELS)
	$(PY) -m soft_gripper_sdre.tools.judging.evaluate --out runs/evaluate $(RUNNER)

# docs/results.md "Robustness to the plant": every registered law (oracles aside) on the grasp and
# the fast grasp, on plants and sensors the model was not trained on, over every core
.PHONY: robustness
robustness: $(KERNELS)
	$(PY) -m soft_gripper_sdre.tools.judging.robustness --out runs/robustness $(RUNNER)

# README "What it achieves" and docs/model.md "Over training seeds": the model and the grasp over 5
# training seeds x 3 draws of the data (as collected, and twice with its float roundings moved),
# the shipped model placed among them; make model's data (collected here if missing) and kernels
.PHONY: seeds
seeds: export OPENBLAS_CORETYPE = Haswell
seeds: export MKL_CBWR = AVX2,STRICT
seeds: export ATEN_CPU_CAPABILITY = avx2
seeds: $(KERNELS)
	test -f data/excitation/x2.npz || $(PY) -m soft_gripper_sdre.tools.learning.collect --out data/excitation
	$(PY) -m soft_gripper_sdre.tools.judging.seeds --data data/excitation --out runs/seeds --seeds 5 --draws 2 --demo $(RUNNER)

# the optional Ray runner of the sweeps (requirements-ray.txt; README "Dependencies")
.PHONY: ray
ray: $(STAMP)
	$(PY) -m pip install --quiet -r requirements-ray.txt -c requirements.txt

# docs/own_gripper.md: the README's own-gripper recipe over DDS on two simulated grippers unlike
# the hand (the plant_driver node), nothing tuned by hand
.PHONY: foreign
foreign: $(KERNELS)
	rm -rf runs/foreign
	-$(PY) -m soft_gripper_sdre.tools.graph.foreign --plant tendon3 --out runs/foreign/tendon3
	-$(PY) -m soft_gripper_sdre.tools.graph.foreign --plant stiff2 --out runs/foreign/stiff2

# docs/deployment.md: two hands on one ROS domain, each in its own namespace with its own clock
two-hands: $(KERNELS)
	$(PY) -m soft_gripper_sdre.tools.graph.hands --out runs/hands

# docs/deployment.md: the graph split across two hosts (two network namespaces joined by a veth
# pair; needs root and iproute2), beside the same grasp on one host, then with the link cut 0.5 s
two-hosts: $(KERNELS)
	$(PY) -m soft_gripper_sdre.tools.graph.two_hosts --out runs/two_hosts

# The lock is pip's own resolution (a dry-run report), so every line names a
# distribution the index serves (pip freeze would also list the dist-info
# names bundled inside the ros-* wheels, which no index has).
lock:
	rm -rf /tmp/sgs-lock && $(PYTHON) -m venv /tmp/sgs-lock
	/tmp/sgs-lock/bin/pip install --quiet --upgrade pip
	/tmp/sgs-lock/bin/pip install --quiet --dry-run --ignore-installed \
	    --report /tmp/sgs-lock/report.json -r requirements.in
	( echo '# Resolved lock of requirements.in (pip dry-run report, Python 3.11, x86_64).'; \
	  echo '# Regenerate: make lock'; \
	  $(PYTHON) -c 'import json; r = json.load(open("/tmp/sgs-lock/report.json")); \
	    print("\n".join(sorted((i["metadata"]["name"] + "==" + i["metadata"]["version"].split("+")[0] \
	    for i in r["install"]), key=str.lower)))' ) > requirements.txt

clean:
	rm -rf $(VENV) build install log *.egg-info
