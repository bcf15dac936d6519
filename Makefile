# The two commands of the README: `make demo` and `make test`. Both build .venv first.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
export OMP_WAIT_POLICY := PASSIVE
# torch first, from PyTorch's CPU wheel index: a bare `torch` requirement pulls a multi-GB CUDA
# build. Where that index can't be reached (5 s, no retries) the default index is used instead.
TORCH := 2.13.0
TORCH_INDEX := https://download.pytorch.org/whl/cpu

.PHONY: demo test bench clean

# Two stamps over one venv: .demo has the extras the demo and the README's commands use, .test adds
# the test peers (pinocchio, roboticstoolbox, pybullet, ...: most of the venv's size). Each step says
# what it installs before pip starts.
$(VENV)/.torch:
	@echo "[1/2] $(VENV) with torch $(TORCH), CPU build ..."
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install --timeout 5 --retries 0 --index-url $(TORCH_INDEX) torch==$(TORCH) \
	  || $(PY) -m pip install torch==$(TORCH)
# -W ignore: without numpy yet, importing torch warns that it cannot initialise NumPy
	$(PY) -W ignore -c "import torch; print('installed torch', torch.__version__, '(CUDA build)' if torch.version.cuda else '(CPU build)')"
	touch $@

$(VENV)/.demo: $(VENV)/.torch pyproject.toml
	@echo "[2/2] iiwa-torch with the extras viz, rl, viewer and fast ..."
	$(PY) -m pip install -e '.[viz,rl,viewer,fast]'
	touch $@

$(VENV)/.test: $(VENV)/.torch pyproject.toml
	@echo "[2/2] iiwa-torch with all extras, the test peers included ..."
	$(PY) -m pip install -e '.[all]'
	touch $@

demo: $(VENV)/.demo
	$(VENV)/bin/iiwa-torch demo && $(PY) -m train.evaluate --model train/policies/ppo_iiwa_reach --goals 1000 --seed 0 --out reports/demo --compare train/policies/panda_gym_reach_sac.json
	@echo "done. Use the venv: source $(VENV)/bin/activate (then iiwa-torch --help), or call $(VENV)/bin/iiwa-torch"

test: $(VENV)/.test
	$(PY) -m pytest -q -n 2
	$(VENV)/bin/ruff check .

# Not tests: side-by-side runs against the peers, results in benchmarks/results/ (the env
# benchmark also needs the peers of the bench extra: pip install -e '.[bench]').
bench: $(VENV)/.test
	for b in fk ik analytic trajectory; do $(PY) benchmarks/bench_$$b.py || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
