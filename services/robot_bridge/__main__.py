"""`python -m services.robot_bridge --help`: the robot bridge (see services/robot_bridge/main.py)."""

from services.robot_bridge.main import main

if __name__ == "__main__":
    main()
