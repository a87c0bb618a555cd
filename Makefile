# The project's toolchain in one place; CI (.ci/run) runs `make lint type test`.
# Every target that needs the environment depends on `setup`, which returns at once when .venv is up to date.
VENV := .venv/bin

.PHONY: setup run test lint format type bench

setup:
	./setup.sh

run: setup
	./launch_scripts/team.sh train

test: setup
	$(VENV)/python -m pytest -q

lint: setup
	$(VENV)/ruff check .
	$(VENV)/ruff format --check .

format: setup
	$(VENV)/ruff check --fix .
	$(VENV)/ruff format .

type: setup
	$(VENV)/mypy

bench: setup
	$(VENV)/htlm bench --json
