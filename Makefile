# wavelight: make demo (the sample scene end to end), make test, make bench.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-$(shell cksum pyproject.toml | cut -d' ' -f1)
DEMO   ?= build/demo
SCENE  ?= spot_sun

.PHONY: venv venv-blender demo test test-slow test-all bench clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	rm -f $(VENV)/.installed-*
	touch $@

# Blender as a Python module (bpy) for tests/test_exports_tools.py, in its own venv: bpy pins
# numpy < 2 and wavelight needs numpy >= 2. ~375 MB download, ~1 GB on disk, ~50 s; the tests find
# .venv-blender/bin/python (or $WAVELIGHT_BPY_PYTHON) and skip the Blender checks without it.
BLENDER_VENV ?= .venv-blender
BPY          ?= bpy==5.0.1
venv-blender: $(BLENDER_VENV)/.installed-bpy

$(BLENDER_VENV)/.installed-bpy:
	test -x $(BLENDER_VENV)/bin/python || $(PYTHON) -m venv $(BLENDER_VENV)
	$(BLENDER_VENV)/bin/python -m pip install --quiet '$(BPY)'
	$(BLENDER_VENV)/bin/python -c 'import bpy; print("bpy", bpy.app.version_string)'
	touch $@

# The main job on the bundled sample scene: a fresh copy in $(DEMO)/$(SCENE), every stage, results printed.
demo: $(STAMP)
	rm -rf $(DEMO)/$(SCENE)
	mkdir -p $(DEMO)
	cp -r sample_data/$(SCENE) $(DEMO)/$(SCENE)
	$(BIN)/wavelight -s $(DEMO)/$(SCENE) calibrate --pattern acircles --pattern-size 4x11 --spacing 10mm
	$(BIN)/wavelight -s $(DEMO)/$(SCENE) register
	$(BIN)/wavelight -s $(DEMO)/$(SCENE) solve
	$(BIN)/wavelight -s $(DEMO)/$(SCENE) compare
	$(BIN)/wavelight -s $(DEMO)/$(SCENE) relight --name evening --rotate 120 --light-exposure -1
	$(BIN)/wavelight -s $(DEMO)/$(SCENE) insert --at 0.8 -0.6 0.25 --radius 0.25 --object-kd 0.9 0.3 0.2
	$(BIN)/wavelight -s $(DEMO)/$(SCENE) export
	$(BIN)/wavelight -s $(DEMO)/$(SCENE) status
	$(BIN)/wavelight -s $(DEMO)/$(SCENE) report
	@echo "results: $(DEMO)/$(SCENE)/camera.json, pose.json (calibrated, registered) and $(DEMO)/$(SCENE)/out"
	@echo "         (calibrate/*_overlay.png, register_overlay.png, light_latlong.exr, light_cross.png, relit.png,"
	@echo "         residual.png, reflectance.json, compare.md, evening.png, insert.png, export/, report/)"
	@echo "truth (camera, pose, light, material): $(DEMO)/$(SCENE)/truth"
	@echo "report: $(DEMO)/$(SCENE)/out/report.md"

# The suite a laptop runs: everything but the tests marked slow (full-resolution checks against the
# Mitsuba renders, the Blender renders, ChArUco detection, the exhaustive route on a second scene).
# The tests run in TEST_JOBS processes (pytest-xdist), each module's tests in one of them (its module
# fixtures built once); TEST_JOBS=0 runs them in this process. Each process peaks at <= ~3.3 GB.
TEST_JOBS ?= 2
PYTEST := $(BIN)/python -m pytest -q -n $(TEST_JOBS) --dist loadfile

test: $(STAMP)
	$(PYTEST) -m "not slow"

# the tests marked slow only (CI runs them after make test)
test-slow: $(STAMP)
	$(PYTEST) -m slow

# everything
test-all: $(STAMP)
	$(PYTEST)

bench: $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[test,bench]'
	$(BIN)/python benchmarks/run.py

clean:
	rm -rf build .pytest_cache

# Batch over many scene folders: make -j2 batch SCENES="path/a path/b ..." [BATCH=build/batch] [R=32]
# [WAVELIGHT_ARGS="more solve options"]. Each scene is its own target (-j runs scenes in parallel):
# `wavelight -s DIR solve -R $(R) $(WAVELIGHT_ARGS)`, then `wavelight -s DIR report`, all output in
# $(BATCH)/NAME.log (NAME: the scene's path with / replaced by _), then $(BATCH)/NAME.ok, or
# $(BATCH)/NAME.failed (scene path, its `Error:` line, the stage). A failed scene does not stop the
# others; `batch` then prints one line per scene (also in $(BATCH)/summary.txt) and fails if any
# scene failed. Scene targets always rerun: wavelight's cache skips the finished stages, so
# rerunning an interrupted batch resumes it. No dependency on the venv's stamp: a batch never
# reinstalls the package under running scenes (run `make venv` first, or pass WAVELIGHT=...).
SCENES         ?=
BATCH          ?= build/batch
R              ?= 32
WAVELIGHT      ?= $(BIN)/wavelight
WAVELIGHT_ARGS ?=

# NAME of a scene: its absolute path (relative to this directory when inside it), / and : -> _
batch_name  = $(subst :,_,$(subst /,_,$(patsubst $(CURDIR)/%,%,$(abspath $(1)))))
# the scenes in the given order, each folder once (a, ./a and a/ are the same folder)
batch_uniq  = $(if $(1),$(firstword $(1)) $(call batch_uniq,$(foreach w,$(wordlist 2,$(words $(1)),$(1)),$(if \
              $(filter $(abspath $(firstword $(1))),$(abspath $(w))),,$(w)))))
BATCH_SCENES  := $(strip $(call batch_uniq,$(SCENES)))
BATCH_TARGETS := $(foreach s,$(BATCH_SCENES),batch-scene-$(call batch_name,$(s)))

ifneq ($(filter batch batch-scene-%,$(MAKECMDGOALS)),)
ifeq ($(BATCH_SCENES),)
$(error batch: SCENES is empty; use: make -j2 batch SCENES="path/a path/b ...")
endif
ifneq ($(words $(sort $(BATCH_TARGETS))),$(words $(BATCH_SCENES)))
$(error batch: two scenes in SCENES get the same log name ($(BATCH)/NAME.log, / -> _); rename one)
endif
ifeq ($(shell command -v '$(WAVELIGHT)'),)
$(error batch: $(WAVELIGHT) not found; run `make venv` first, or pass WAVELIGHT=path/to/wavelight)
endif
endif

$(foreach s,$(BATCH_SCENES),$(eval batch-scene-$(call batch_name,$(s)): BATCH_SCENE := $(s)))

.PHONY: batch $(BATCH_TARGETS)

# One scene. Succeeds even when the scene fails (so make goes on with the others without -k);
# the markers say how it went.
$(BATCH_TARGETS):
	@scene='$(BATCH_SCENE)'; out='$(BATCH)/$(@:batch-scene-%=%)'; \
	mkdir -p '$(BATCH)' && rm -f "$$out.ok" "$$out.failed" || exit 1; \
	echo "batch: $$scene: solve + report -> $$out.log"; \
	stage=solve; \
	'$(WAVELIGHT)' -s "$$scene" solve -R '$(R)' $(WAVELIGHT_ARGS) >"$$out.log" 2>&1 && \
	{ stage=report; '$(WAVELIGHT)' -s "$$scene" report >>"$$out.log" 2>&1; }; \
	status=$$?; \
	if [ $$status -eq 0 ]; then \
	  echo "$$scene" >"$$out.ok"; \
	  echo "batch: $$scene: ok"; \
	else \
	  err=$$(grep '^Error:' "$$out.log" | tail -n 1); \
	  [ -n "$$err" ] || err="$$stage exited with status $$status: $$(grep . "$$out.log" | tail -n 1)"; \
	  printf '%s\n%s\n%s\n' "$$scene" "$$err" "stage $$stage, exit status $$status, log $$out.log" >"$$out.failed"; \
	  echo "batch: $$scene: FAILED in $$stage"; \
	fi

batch: $(BATCH_TARGETS)
	@line() { \
	  if [ -f "$(BATCH)/$$2.ok" ]; then echo "ok      $$1"; \
	  elif [ -f "$(BATCH)/$$2.failed" ]; then echo "FAILED  $$1: $$(sed -n 2p "$(BATCH)/$$2.failed")"; \
	  else echo "FAILED  $$1: no result (see $(BATCH)/$$2.log)"; fi; \
	}; \
	{ $(foreach s,$(BATCH_SCENES),line '$(s)' '$(call batch_name,$(s))';) } >'$(BATCH)/summary.txt'; \
	echo "batch summary ($(BATCH)/summary.txt):"; cat '$(BATCH)/summary.txt'; \
	failed=$$(grep -c '^FAILED' '$(BATCH)/summary.txt'); \
	if [ "$$failed" -gt 0 ]; then \
	  echo "batch: $$failed of $(words $(BATCH_SCENES)) scenes failed:$$(sed -n 's/^FAILED  \([^:]*\):.*/ \1/p' '$(BATCH)/summary.txt' | tr -d '\n')"; \
	  exit 1; \
	fi; \
	echo "batch: all $(words $(BATCH_SCENES)) scenes ok"
