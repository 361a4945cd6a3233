"""Measurement results: one directory per measurement (temp dir + rename), figure, Mitsuba medium."""

from trimeter.results.writer import Measurement, Parameters, write_measurement

__all__ = ["Measurement", "Parameters", "write_measurement"]
