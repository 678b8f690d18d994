"""The robot bridge: one process per gripper, serving the real servos and camera (or the stand-in)."""
