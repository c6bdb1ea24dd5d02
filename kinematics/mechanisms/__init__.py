"""Mechanisms: correlative joints (law, fitting, transfer, OpenSim export, recovered mechanisms), transmission elements, distance chords, coupled spines and their measures."""
