"""Plants: the plant classes and their checks, the hydraulic actuator and the registry."""
