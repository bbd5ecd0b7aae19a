PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: venv test demo bench clean docker-test

venv: $(BIN)/.installed

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e ".[all]"
	touch $@

test: venv
	$(BIN)/python -m pytest -q

demo: venv
	$(BIN)/bubsub demo --out demo-output --overwrite

bench: venv
	$(BIN)/python -m bubsub.bench

# Builds the image and runs the compose project for real (needs Docker; not part of `test`).
docker-test:
	bash docker/test.sh

clean:
	rm -rf $(VENV) demo-output build *.egg-info
