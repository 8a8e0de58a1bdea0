# Convenience aliases for the two README commands; dev.py does the work (it needs only python3 and pip).
.PHONY: sim test bench lint
sim:
	python3 dev.py sim
test:
	python3 dev.py test
bench:
	python3 dev.py appliance bench
lint:
	.venv/bin/lint-imports
