"""Mechanisms: correlative joints, transmission elements, distance chords and coupled spines."""
