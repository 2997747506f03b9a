"""The pipeline's stages over a rig: fit, tune, cross-validation, replay, transfer, evaluation."""
