"""Scenario input: the spec, the TOML parser and writer, the ``[sweep]`` table and measured data."""
