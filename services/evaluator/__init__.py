"""The evaluator service: deterministic evaluation episodes every eval_every global env steps."""
