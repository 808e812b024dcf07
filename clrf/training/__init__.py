"""Training and evaluation: the trainer (trainer.py), the run configuration (config.py), the
model kinds (models.py), the memory guard of a configured run (budget.py) and the image
metrics (metrics.py, perceptual.py)."""
