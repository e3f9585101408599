.PHONY: setup test demo bench clean
VENV := .venv

setup:
	./setup.sh

test: setup
	$(VENV)/bin/python -m pytest -q

demo: setup
	$(VENV)/bin/cpdetect demo

bench: setup
	$(VENV)/bin/python bench/detect_bench.py

clean:
	rm -rf build dist *.egg-info .pytest_cache
