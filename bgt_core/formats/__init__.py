"""Readers and writers for the published dataset's file formats (see docs/formats.md).

The modules here are standard-library only at import time; functions that return pandas
objects import pandas when called, so the agent can read mbd files without it.
"""
