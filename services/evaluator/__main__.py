"""`python -m services.evaluator --help`: the evaluator process (see services/evaluator/evaluator.py)."""

from services.evaluator.evaluator import main

if __name__ == "__main__":
    main()
