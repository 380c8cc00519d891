"""Shared physics of the EMA: mechanics, control, sensors, commutation and the two motor models."""
