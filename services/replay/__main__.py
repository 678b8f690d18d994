"""`python -m services.replay --help`: the replay service (see services/replay/service.py)."""

from services.replay.service import main

if __name__ == "__main__":
    main()
