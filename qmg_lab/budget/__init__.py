"""Predictions from a configuration alone: the CLSF noise budget and the sweep's accuracy and linearity."""
