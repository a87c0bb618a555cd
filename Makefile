# The project's toolchain in one place; CI (.ci/run) runs `make lint type test test-slow`.
# Every target that needs the environment depends on `setup`, which returns at once when .venv is up to date.
VENV := .venv/bin

.PHONY: setup setup-browser run test test-slow lint format type bench

setup:
	./setup.sh

# the headless browser of the people's pages' tests (Debian's chromium and chromium-driver, with apt)
setup-browser:
	tests/setup-browser.sh

run: setup
	./launch_scripts/team.sh train

test: setup
	$(VENV)/python -m pytest -q

# the tests marked slow: the fault and attack tests of the ROS runtime (kills, restarts, network cut, flood, fuzzed
# training topics, forgeries beyond one), the batch-1 and other variants of the equivalence tests, the network tests
# (namespaces, partition, bad links, clock offsets), the quick reproduction and the install test of the packages in a
# fresh venv (about 30 min; the default run keeps one test of each family, about 10 min)
test-slow: setup
	$(VENV)/python -m pytest -q -m slow

lint: setup
	$(VENV)/ruff check .
	$(VENV)/ruff format --check .
	$(VENV)/lint-imports

format: setup
	$(VENV)/ruff check --fix .
	$(VENV)/ruff format .

type: setup
	$(VENV)/mypy

bench: setup
	$(VENV)/htlm bench --json
