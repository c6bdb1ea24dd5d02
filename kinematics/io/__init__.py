"""Readers and writers at the file boundary: C3D, TRC/MOT/STO, OpenSim models, force plates, marker sets."""
