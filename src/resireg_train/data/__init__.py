"""Caption streaming for training and the synthetic scenes used by tests and smoke runs."""
