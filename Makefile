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
# A parent shell may carry the wheels' bootstrap flag from another venv.
unexport _ROS_WHEELS_BOOTSTRAP_COMPLETE

ROS_WHEELS := ros-rclpy ros-rmw-fastrtps-cpp ros-std-msgs ros-geometry-msgs \
              ros-sensor-msgs ros-diagnostic-msgs ros-rosgraph-msgs ros-builtin-interfaces \
              ros-trajectory-msgs ros-visualization-msgs
PY_DEPS    := numpy scipy numba matplotlib pyyaml rosbags mcap mcap-ros2-support viser
TEST_DEPS  := pytest pytest-xdist ruff colcon-core colcon-ros colcon-package-information playwright

DEMO_OUT ?= out/demo

.PHONY: demo test test-fast lint bench bench-view venv clean

venv: $(KERNELS)

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
	$(BIN)/python -c 'import rclpy, sensor_msgs.msg, stewart63_ros'
	touch $(STAMP)

$(KERNELS): $(STAMP) $(wildcard stewart63_ros/core/*.py)
	$(BIN)/python -m stewart63_ros.core.precompile
	touch $(KERNELS)

demo: $(KERNELS)
	$(BIN)/python -m stewart63_ros.tools.demo --out $(DEMO_OUT)

# The MuJoCo agreement test must run here, not skip: make installed the extra.
test: $(KERNELS)
	STEWART63_REQUIRE_MUJOCO=1 $(BIN)/python -m pytest -q test

# The numerics only: no DDS, no processes (markers in setup.cfg, test/conftest.py).
test-fast: $(KERNELS)
	$(BIN)/python -m pytest -q -m "not slow" test

# pyflakes, pycodestyle, bugbear, blind except (ruff.toml).
lint: $(STAMP)
	$(BIN)/ruff check .

# Every figure, medians of repeated runs, into bench/results.json (README, Performance).
bench: $(KERNELS)
	$(BIN)/python bench/bench_all.py

# The realtime loop without and with the live view open (a client, a browser).
bench-view: $(KERNELS)
	$(BIN)/python bench/bench_view.py

clean:
	rm -rf $(VENV) build install log out *.egg-info
