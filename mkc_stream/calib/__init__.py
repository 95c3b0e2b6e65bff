"""Magnetometer (and later accelerometer/gyroscope) calibrators, quality metrics and gates."""
