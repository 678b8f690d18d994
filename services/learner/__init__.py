"""The learner service: replay batches in, agent updates, weights out, FastAPI status."""
