# The two commands of the README: `make demo` and `make test`. Both build .venv first.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
export OMP_WAIT_POLICY := PASSIVE

.PHONY: demo test bench clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0  # the CPU build, before anything can pull a CUDA one
	$(PY) -m pip install -q -e '.[all]'
	touch $@

demo: $(VENV)/.installed
	$(VENV)/bin/iiwa-torch demo && $(PY) -m train.evaluate --model train/policies/ppo_iiwa_reach --goals 1000 --seed 0 --out reports/demo --compare train/policies/panda_gym_reach_sac.json

test: $(VENV)/.installed
	$(PY) -m pytest -q -n 2
	$(VENV)/bin/ruff check .

# Not tests: side-by-side runs against the peers, results in benchmarks/results/ (the env
# benchmark also needs the peers of the bench extra: pip install -e '.[bench]').
bench: $(VENV)/.installed
	for b in fk ik analytic trajectory; do $(PY) benchmarks/bench_$$b.py || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
