"""Calibration: fitting routines and the camera / vision code (OpenCV behind one adapter)."""
