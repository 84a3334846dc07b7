# pointfence: `make demo` runs the main job on the embedded defaults, `make test` runs every test.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
# No "A new release of pip is available" notice, and -qq: pip prints errors, not the build
# backend's notices about this layout (a top-level `pointfence/` folder beside the mapped
# packages, an editable install), which a user cannot act on: `make` prints what a user can.
PIP    := $(VENV)/bin/pip --disable-pip-version-check

.PHONY: demo test install dev ctest clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip

install: $(PY)
	$(PIP) install -qq -e .

dev: $(PY)
	$(PIP) install -qq -e ".[dev]"

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
