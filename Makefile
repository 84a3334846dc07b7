# pointfence: `make demo` runs the main job on the embedded defaults, `make test` runs every test.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
# -q and no "A new release of pip is available" notice: `make` prints only what a user can act on.
PIP    := $(VENV)/bin/pip --disable-pip-version-check

.PHONY: demo test install dev ctest clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip

install: $(PY)
	$(PIP) install -q -e .

dev: $(PY)
	$(PIP) install -q -e ".[dev]"

demo: install
	$(VENV)/bin/pointfence demo

# C tests (the C client SDK) are built and run by ctest when their CMake project exists.
ctest:
	@if [ -f clients/c/CMakeLists.txt ]; then \
	  cmake -S clients/c -B build/clients-c -DCMAKE_BUILD_TYPE=Release >/dev/null && \
	  cmake --build build/clients-c -j 2 >/dev/null && \
	  (cd build/clients-c && ctest --output-on-failure); \
	else echo "no C tests yet"; fi

test: dev ctest
	$(PY) -m pytest -q

clean:
	rm -rf build $(VENV) *.egg-info
