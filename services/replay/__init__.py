"""The replay service: the replay library (shared/replay) served over Zenoh."""
