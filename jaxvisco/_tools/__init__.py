"""Tools built on the time loop: identification, batching, the semi-discrete ODE, material drivers and resuming runs."""
