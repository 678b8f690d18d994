"""`python -m services.learner --help`: the learner process (see services/learner/learner.py)."""

from services.learner.learner import main

if __name__ == "__main__":
    main()
