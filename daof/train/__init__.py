"""Training machinery shared by every recipe: factories, the DSAC-T loop, checkpoints."""
