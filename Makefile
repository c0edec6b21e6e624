# Two entry points: `make run` (the simulated stack, recorded and summarised) and `make test`.
# Both bring .venv up to date first (scripts/setup.sh; seconds when nothing changed).
PY       := .venv/bin/python
GRAPH    ?= sim
DURATION ?= 0        # wall-clock seconds; 0: until the scenario ends (the simulator ends the run)
SCENARIO ?=
VEHICLE  ?=
SEED     ?=
VIEW     ?=
RUN      ?= runs/$(shell date -u +%Y%m%d-%H%M%S)

.PHONY: setup run test

setup:
	@scripts/setup.sh

run: setup
	$(if $(VIEW),@echo "live view: Foxglove -> Open connection -> ws://localhost:8765; layout config/foxglove/drift_layout.json (docs/live_view.md)")
	$(PY) scripts/run_stack.py --graph $(GRAPH)$(if $(VIEW),_view) --duration $(DURATION) \
		--bag $(RUN)/bag --log-dir $(RUN)/logs $(if $(SCENARIO),--scenario $(SCENARIO)) \
		$(if $(VEHICLE),--vehicle $(VEHICLE)) $(if $(SEED),--seed $(SEED)) $(ARGS)

test:
	@.ci/run $(ARGS)
