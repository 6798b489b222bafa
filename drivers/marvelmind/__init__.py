"""Marvelmind indoor positioning: a sans-I/O protocol parser and a serial reader."""
