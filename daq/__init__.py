"""Acquisition: sources (drivers), the virtual rig, the recorder and run storage."""
