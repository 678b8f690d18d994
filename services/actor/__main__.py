"""`python -m services.actor --help`: one actor process (see services/actor/actor.py)."""

from services.actor.actor import main

if __name__ == "__main__":
    main()
