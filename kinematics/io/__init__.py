"""Readers and writers at the file boundary: C3D, TRC/MOT/STO, OpenSim models and IK setups, force plates, external loads, marker sets."""
