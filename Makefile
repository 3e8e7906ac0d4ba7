# One-command entry points; each builds .venv/ itself on a fresh machine.
PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.installed
# PyTorch's CPU-only builds: torch comes from here, unless a local wheel of the pinned
# version is found first (pip's --find-links of this machine); PyPI's Linux torch pulls CUDA
# (GBs). Its dependencies come with requirements.txt.
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
TORCH := $(shell sed -n 's/^\(torch==[^ ]*\).*/\1/p' requirements.txt)
# The ROS 2 Jazzy launch packages as wheels, for the launch-file tests (.ci/launch_wheels
# says where it looks; set LAUNCH_WHEELS=DIR to choose). Without them those tests are
# skipped with the reason, except under LOMPR_REQUIRE_LAUNCH=1 (CI), where that is an error.
# launch_ros imports composition_interfaces, a message package without a wheel: the shim
# beside the wheels goes into the environment's site-packages.
LAUNCH_WHEEL_DIR := $(shell LAUNCH_WHEELS='$(LAUNCH_WHEELS)' .ci/launch_wheels)
LAUNCH_STAMP := $(VENV)/.launch-installed
SITE_PACKAGES = $(shell $(VENV)/bin/python -c 'import sysconfig; print(sysconfig.get_path("purelib"))')

.PHONY: venv launch-wheels test test-fast lint demo bench clean

venv: $(STAMP)

$(STAMP): requirements.txt setup.py package.xml
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade pip
	$(VENV)/bin/python -m pip install --quiet --no-deps --no-index '$(TORCH)' 2>/dev/null \
		|| $(VENV)/bin/python -m pip install --quiet --no-deps --index-url $(TORCH_INDEX) \
		'$(TORCH)'
	$(VENV)/bin/python -m pip install --quiet -r requirements.txt
	$(VENV)/bin/python -m pip install --quiet --no-deps -e .
	touch $(STAMP)

launch-wheels: $(LAUNCH_STAMP)

$(LAUNCH_STAMP): $(STAMP) $(wildcard $(LAUNCH_WHEEL_DIR)/*.whl)
ifeq ($(LAUNCH_WHEEL_DIR),)
	@if [ -n "$$LOMPR_REQUIRE_LAUNCH" ]; then \
		echo 'error: no ROS 2 launch wheels found (.ci/launch_wheels; LAUNCH_WHEELS=DIR)' >&2; \
		exit 1; fi
	@echo 'no ROS 2 launch wheels found (.ci/launch_wheels; LAUNCH_WHEELS=DIR): the' \
		'launch-file tests are skipped'
else
	$(VENV)/bin/python -m pip install --quiet --no-deps --no-index \
		--find-links '$(LAUNCH_WHEEL_DIR)' launch launch-xml launch-yaml launch-ros
	rm -rf '$(SITE_PACKAGES)/composition_interfaces'
	cp -r --no-preserve=mode '$(LAUNCH_WHEEL_DIR)/shims/composition_interfaces' '$(SITE_PACKAGES)'
	touch $(LAUNCH_STAMP)
endif

test: venv launch-wheels
	$(VENV)/bin/python -m pytest -q test

test-fast: venv launch-wheels  # everything but the slow tests (closed loops, colcon build)
	$(VENV)/bin/python -m pytest -q -m "not slow" test

lint: venv
	$(VENV)/bin/ruff check lompr_predictor test bench tools
	$(VENV)/bin/mypy
	$(VENV)/bin/python tools/spdx_headers.py --check

demo: venv
	$(VENV)/bin/lompr demo

bench: venv
	for script in bench/bench_*.py bench/soak_*.py; do $(VENV)/bin/python $$script || exit 1; done

clean:
	rm -rf $(VENV) build install log .pytest_cache
