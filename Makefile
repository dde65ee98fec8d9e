# Two commands for a new user: `make demo` and `make test` (docs/interface.md).
# Where rclpy is already importable (a sourced /opt/ros), the venv sees the
# system packages; elsewhere the ROS 2 wheels come from the package index.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
# numba's cache does not follow kernels across files: recompile all of them
# whenever a core file changes (precompile clears the cache first).
KERNELS := $(VENV)/.kernels
# Bytecode of the package, its tests and benches, written once here: where
# PYTHONDONTWRITEBYTECODE is set, each process `make test` starts compiled
# every module it imported again (0.15 s of CPU for a node). A stale file is
# only ignored: Python checks the source's mtime.
BYTECODE := $(VENV)/.bytecode
# A parent shell may carry the wheels' bootstrap flag from another venv.
unexport _ROS_WHEELS_BOOTSTRAP_COMPLETE

ROS_WHEELS := ros-rclpy ros-rmw-fastrtps-cpp ros-std-msgs ros-geometry-msgs \
              ros-sensor-msgs ros-diagnostic-msgs ros-rosgraph-msgs ros-builtin-interfaces \
              ros-trajectory-msgs ros-visualization-msgs ros-std-srvs
PY_DEPS    := numpy scipy numba matplotlib pyyaml rosbags mcap mcap-ros2-support viser \
              dask distributed python-can canopen setproctitle
TEST_DEPS  := pytest pytest-xdist ruff colcon-core colcon-ros colcon-package-information playwright \
              xmlschema junitparser

DEMO_OUT ?= out/demo
# The packaged machine of `make demo`: 6-3 (the paper's) or 6-6 (config/hexapod66.yaml).
GEOMETRY ?= 6-3

.PHONY: demo test test-fast test-stress lint bench bench-view venv clean

venv: $(KERNELS) $(BYTECODE)

$(STAMP): setup.py package.xml Makefile
	@if $(PYTHON) -c 'import rclpy' >/dev/null 2>&1; then \
	  echo "rclpy found on the system: venv with --system-site-packages"; \
	  [ -x $(BIN)/python ] || $(PYTHON) -m venv --system-site-packages $(VENV); \
	  $(BIN)/pip install -q --upgrade pip; \
	else \
	  echo "no system rclpy: installing the ROS 2 Python wheels into $(VENV)"; \
	  [ -x $(BIN)/python ] || $(PYTHON) -m venv $(VENV); \
	  $(BIN)/pip install -q --upgrade pip; \
	  $(BIN)/pip install -q $(ROS_WHEELS); \
	fi
	$(BIN)/pip install -q $(PY_DEPS) $(TEST_DEPS)
	$(BIN)/pip install -q -e '.[bench]'
	$(BIN)/python -c 'import rclpy, sensor_msgs.msg, std_srvs.srv, stewart63_ros'
	touch $(STAMP)

$(KERNELS): $(STAMP) $(wildcard stewart63_ros/core/*.py stewart63_ros/core/*/*.py)
	$(BIN)/python -m stewart63_ros.core.precompile
	touch $(KERNELS)

$(BYTECODE): $(STAMP) $(shell find stewart63_ros test bench -name '*.py' 2>/dev/null)
	$(BIN)/python -m compileall -q -j 0 stewart63_ros test bench
	touch $(BYTECODE)

demo: $(KERNELS) $(BYTECODE)
	$(BIN)/python -m stewart63_ros.tools.demo --out $(DEMO_OUT) --geometry $(GEOMETRY)

# The MuJoCo agreement test must run here, not skip: make installed the extra.
# Two workers (pytest-xdist): most DDS tests wait on discovery and on the
# rig's pace, not on a core; each test leases its own ROS domain. Work
# stealing: a worker that is done takes tests queued on the other (with the
# default scheduling one worker sat idle for the suite's last 1.5-2 minutes).
TEST_WORKERS ?= 2
# pytest keeps its rewritten test modules only where bytecode may be written.
test: $(KERNELS) $(BYTECODE)
	env -u PYTHONDONTWRITEBYTECODE STEWART63_REQUIRE_MUJOCO=1 \
	  $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist worksteal test

# The DDS tests three times in a row while another process keeps a core
# busy (test/stress.py): a loaded machine may make the rig slower, never wrong.
STRESS_ROUNDS ?= 3
test-stress: $(KERNELS) $(BYTECODE)
	$(BIN)/python test/stress.py --rounds $(STRESS_ROUNDS) -- -n $(TEST_WORKERS) -m dds test

# The numerics only: no DDS, no processes (markers in setup.cfg, test/conftest.py).
test-fast: $(KERNELS) $(BYTECODE)
	$(BIN)/python -m pytest -q -m "not slow" test

# pyflakes, pycodestyle, bugbear, blind except, import order (ruff.toml).
lint: $(STAMP)
	$(BIN)/ruff check .

# Every figure, medians of repeated runs, into bench/results.json (docs/performance.md).
bench: $(KERNELS) $(BYTECODE)
	$(BIN)/python bench/bench_all.py

# The realtime loop without and with the live view open (a client, a browser).
bench-view: $(KERNELS) $(BYTECODE)
	$(BIN)/python bench/bench_view.py

clean:
	rm -rf $(VENV) build install log out *.egg-info
