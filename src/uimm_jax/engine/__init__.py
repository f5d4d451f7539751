"""The pure-JAX engine: Kalman steps, IMM mixing, the diagnosers, truth, scans, metrics.

Nothing here reads files or knows about scenarios; everything above (plants, scenario,
studies, cli) imports from here and never the other way.
"""
