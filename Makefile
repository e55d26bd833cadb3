# make setup: apt packages (open3d's off-screen rendering libraries, python3-venv, headless Chromium and
#             its driver for the report page's browser test), a .venv,
#             and the package with its dev extra. Idempotent: re-runs only when pyproject.toml changes.
#             Then the numba kernels a first run uses compile, two processes side by side
#             (gt3dkit.commands.warmup). pip writes no bytecode (--no-compile: 16-20 s of it, file by
#             file, before the kernels started): Python writes it as modules are first imported, or,
#             where PYTHONDONTWRITEBYTECODE is set and nothing would, the warm-up writes that of
#             what gt3dkit and its tests import beside the kernels' compilation (--bytecode; without
#             it every process compiled numpy, scipy, ... from source again: make test 254 s ->
#             366 s here).
# make demo:  reconstruct the bundled real MultiviewX and Panoptic data, print errors, write reports.
# make test:  the test suite (benchmarks excluded; see make bench), one pytest-xdist process per
#             core, each test file whole in one (its module fixtures built once): 264 s -> 180 s
#             on 2 cores.
VENV ?= .venv
PY := $(VENV)/bin/python
APT_PKGS := python3-venv libusb-1.0-0 libvulkan1 mesa-vulkan-drivers libegl1 libgl1 libgomp1 libegl-mesa0 libgl1-mesa-dri \
            chromium chromium-driver

.PHONY: setup demo test bench bench-env labels-env pose2sim-env movement-env bench-long lint clean

setup: $(VENV)/.installed
	@$(PY) -m compileall -q gt3dkit >/dev/null  # bytecode kept, also where PYTHONDONTWRITEBYTECODE is set

$(VENV)/.installed: pyproject.toml
	@missing=""; for p in $(APT_PKGS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing apt packages:$$missing"; \
	  SUDO=""; [ "$$(id -u)" -eq 0 ] || SUDO=sudo; \
	  $$SUDO apt-get update -qq && $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; \
	fi
	@test -x $(PY) || python3 -m venv $(VENV)
	@echo "installing gt3dkit and its dependencies into $(VENV) (pip; about half a minute)"
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q --no-compile -e ".[dev]"
	$(PY) -m gt3dkit.commands.warmup $(if $(PYTHONDONTWRITEBYTECODE),--bytecode,)
	@touch $@

demo: setup
	$(VENV)/bin/gt3d demo --out out/demo

test: setup labels-env
	$(PY) -m pytest -q -n auto --dist loadfile

bench: setup
	$(PY) scripts/box_targets.py

# aniposelib (pyproject's bench extra) in an environment of its own, for scripts/bench_long.py
bench-env: setup .venv-bench/.installed

.venv-bench/.installed: pyproject.toml
	@test -x .venv-bench/bin/python || python3 -m venv .venv-bench
	.venv-bench/bin/python -m pip install -q --upgrade pip
	.venv-bench/bin/python -m pip install -q $$($(PY) -c "import tomllib; print(' '.join(tomllib.load(open('pyproject.toml', 'rb'))['project']['optional-dependencies']['bench']))")
	@touch $@

# Pose2Sim's synchronization step (scripts/people_targets.py section 4b) in an environment of its own:
# pose2sim itself without its dependencies (OpenSim, the pose estimators, Qt: other steps'), and what
# its synchronization and common modules import
POSE2SIM = pose2sim==0.10.49
POSE2SIM_DEPS = numpy pandas scipy matplotlib opencv-python-headless anytree rtoml c3d
pose2sim-env: .venv-pose2sim/.installed

.venv-pose2sim/.installed: Makefile
	@test -x .venv-pose2sim/bin/python || python3 -m venv .venv-pose2sim
	.venv-pose2sim/bin/python -m pip install -q --upgrade pip
	.venv-pose2sim/bin/python -m pip install -q $(POSE2SIM_DEPS)
	.venv-pose2sim/bin/python -m pip install -q --no-deps $(POSE2SIM)
	@touch $@

# movement (an independent writer of DeepLabCut's files, scripts/animal_targets.py section 5) in an
# environment of its own: movement itself without its dependencies (napari, Qt, netCDF: its viewers'
# and other formats'), what its io modules import, and sleap-io without its drawing and cloud ones
MOVEMENT = movement==0.15.0 sleap-io==0.9.5
MOVEMENT_DEPS = numpy pandas h5py tables xarray attrs loguru pyyaml tqdm pynwb ndx-pose imageio shapely simplejson lazy-loader
movement-env: .venv-movement/.installed

.venv-movement/.installed: Makefile
	@test -x .venv-movement/bin/python || python3 -m venv .venv-movement
	.venv-movement/bin/python -m pip install -q --upgrade pip
	.venv-movement/bin/python -m pip install -q $(MOVEMENT_DEPS)
	.venv-movement/bin/python -m pip install -q --no-deps $(MOVEMENT)
	@touch $@

# datumaro (pyproject's labels-check extra: CVAT's own reader, for the tests of gt3d project's
# CVAT files) in an environment of its own: it pins opencv-python-headless 4 and pandas 2
labels-env: setup .venv-labels/.installed

.venv-labels/.installed: pyproject.toml
	@test -x .venv-labels/bin/python || python3 -m venv .venv-labels
	.venv-labels/bin/python -m pip install -q --upgrade pip
	.venv-labels/bin/python -m pip install -q $$($(PY) -c "import tomllib; print(' '.join(tomllib.load(open('pyproject.toml', 'rb'))['project']['optional-dependencies']['labels-check']))")
	@touch $@

bench-long: setup bench-env
	$(PY) scripts/bench_long.py

lint: setup
	$(VENV)/bin/ruff check gt3dkit tests scripts

clean:
	rm -rf out .pytest_cache
