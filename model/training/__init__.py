"""Training, losses, data pipeline and evaluation for IFNet (needs torch)."""
