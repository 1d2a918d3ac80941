"""The test suite: seeded, deterministic, against the real drivers and the simulated devices over real transports."""
