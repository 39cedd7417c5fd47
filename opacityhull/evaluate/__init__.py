"""Evaluation: held-out views and ground truth, above the stages it judges."""
