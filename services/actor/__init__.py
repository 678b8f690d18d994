"""The actor service: an environment, a local policy copy, and a stream of transitions to the replay."""
