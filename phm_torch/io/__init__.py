"""File formats: measurement CSV files."""

from .measurement_csv import REQUIRED, Measurement, read_measurement, write_measurement

__all__ = ["REQUIRED", "Measurement", "read_measurement", "write_measurement"]
