# The two commands of the README. Each installs what it needs first (scripts/setup.sh).
.PHONY: annotate test setup benchmarks

annotate:            ## serve the browser annotation tool on the bundled sample sequence
	bash scripts/setup.sh
	.venv/bin/annotate

test:                ## run the test suite
	bash scripts/setup.sh test
	.venv/bin/python -m pytest -q

benchmarks:          ## speed and accuracy figures (minutes)
	bash scripts/setup.sh test
	for b in benchmarks/bench_*.py; do .venv/bin/python $$b || exit 1; done
