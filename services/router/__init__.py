"""A Zenoh router for a run: `python -m services.router --listen tcp/0.0.0.0:7447`."""
