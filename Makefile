# Two commands do all set-up on a fresh machine: `make serve` and `make test`.
# Python 3.11, 3.12 or 3.13 (`make test PY=python3.12`).
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
HOST ?= 127.0.0.1
PORT ?= 8000

.PHONY: install serve test test-loaded test-all lint typecheck summary eval eval-final perf clean browser viewer-vendor servers image novelty calibration

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

# torch first, pinned to the local CPU wheel, so nothing later pulls a CUDA build
$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e '.[server,test]'
	touch $@

install: $(VENV)/.installed

serve: install
	$(BIN)/stylestream serve --host $(HOST) --port $(PORT)

# Re-fetch three.js for the browser viewer from the npm registry (checked against its sha512)
viewer-vendor:
	sh clients/viewer/vendor/fetch-three.sh

# Chromium for the browser-viewer tests (Debian package); without apt they are skipped, saying why
browser:
	@command -v chromium >/dev/null 2>&1 || { command -v apt-get >/dev/null 2>&1 && \
		(apt-get update -qq && apt-get install -y -qq chromium >/dev/null) || \
		echo "chromium not installed: the viewer's browser tests will be skipped"; }

# redis-server and nginx for the two-replica and drain tests (Debian packages, started by the
# tests themselves on free ports); without apt those tests are skipped, saying why
servers:
	@{ command -v redis-server >/dev/null 2>&1 && { command -v nginx >/dev/null 2>&1 || test -x /usr/sbin/nginx; }; } || \
		{ command -v apt-get >/dev/null 2>&1 && \
		(apt-get update -qq && apt-get install -y -qq redis-server nginx >/dev/null) || \
		echo "redis-server/nginx not installed: the replica and drain tests will be skipped"; }

# The service image, stylestream:latest (docs/deploy.md): as root, container-base.sh first installs
# podman and the registry-free python:3.11-slim base (idempotent); build-image.sh stages the torch CPU wheel
image:
	@[ "$$(id -u)" != 0 ] || bash ../shared/tools/container-base.sh
	bash docker/build-image.sh

# ruff's lint and format check; mypy over service/ and models/ ([tool.mypy] in pyproject.toml)
lint: install
	$(BIN)/python -m ruff check .
	$(BIN)/python -m ruff format --check .

typecheck: install
	$(BIN)/python -m mypy

# pytest-xdist: one worker per core and one more, at most 4 (each loads torch and the models): the
# workers wait on servers and subprocesses about a third of the time (2 cores: tests 318 -> 292 s
# with the third). A test file stays on one worker, so its module fixtures (servers, loaded models)
# start once. TEST_JOBS=0: one process
TEST_JOBS ?= $(shell echo $$(( $$(nproc) + 1 )))
PYTEST := $(BIN)/python -m pytest -q -n $(TEST_JOBS) --maxprocesses 4 --dist loadfile

# mypy runs beside pytest, whose workers wait on servers and subprocesses about a third of the time;
# niced, so it takes those gaps rather than CPU from the kernel warm-up the workers wait for
test: install browser servers lint
	@mkdir -p .cache; nice -n 10 $(BIN)/python -m mypy > .cache/typecheck.log 2>&1 & typecheck=$$!; \
	$(PYTEST) -m "not slow"; tests=$$?; \
	wait $$typecheck; types=$$?; echo "$(BIN)/python -m mypy"; cat .cache/typecheck.log; \
	[ $$tests = 0 ] && [ $$types = 0 ]

test-loaded: install browser servers  # the suite beside four busy processes (tests/busy.py)
	$(BIN)/python -m tests.busy 4 -- $(PYTEST) -m "not slow"

test-all: install
	$(PYTEST)

perf: install
	$(BIN)/python -m clients.perf_report $(PERF_ARGS)

summary: install
	$(BIN)/python -m models.data summary

# the sealed evaluation (docs/evaluation.md): every choice is made on `make eval` (validation
# inputs, out/eval-val/); `make eval-final` scores the test inputs once a change is finished and
# records the run in docs/eval/final_runs.md
eval: install
	$(BIN)/python -m models.eval

eval-final: install
	$(BIN)/python -m models.eval --final

# each method's unseen-content reference, from the clips it was trained on (models/motion/novelty.py)
novelty: install
	$(BIN)/python -m models.motion.novelty fit --method lti --datasets bandai-namco-2 --styles normal
	$(BIN)/python -m models.motion.novelty fit --method erd --datasets bandai-namco-2
	$(BIN)/python -m models.motion.novelty fit --method lpn --datasets bandai-namco-1,bandai-namco-2 \
		--contents walk,run,dash,walk-back,walk-left,walk-right,walk-turn-left,walk-turn-right

# each method's posture range, from the neutral clips its sessions stand in for (models/motion/calibration.py);
# shipped for Style-ERD only: on validation LTI's one passing running row lost a clip (docs/eval/ablation.md)
calibration: install
	$(BIN)/python -m models.motion.calibration fit --method erd --datasets bandai-namco-2 --styles normal

clean:
	rm -rf $(VENV) .cache .pytest_cache
