"""Studies: run, sweep and tune a scenario, the float32 option and the ``imm_filter`` API."""
