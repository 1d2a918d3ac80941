"""Device drivers (protocol adapters) for the servo controller and the CMM."""
