# wavelight: make demo (the sample scene end to end), make test, make bench.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-$(shell cksum pyproject.toml | cut -d' ' -f1)
DEMO   ?= build/demo
SCENE  ?= spot_sun

.PHONY: venv demo test test-fast bench clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	rm -f $(VENV)/.installed-*
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

test: $(STAMP)
	$(BIN)/python -m pytest -q

# everything but the slow full-resolution checks against Mitsuba
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow"

bench: $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[test,bench]'
	$(BIN)/python benchmarks/run.py

clean:
	rm -rf build .pytest_cache
