"""Synthetic phantoms with exactly known anatomy (bones, landmarks, axes, joint frames).

>>> from phantoms import make_phantom
>>> ph = make_phantom(seed=0)
>>> ph.sdf("femur_r", pts)       # signed distance, metres, negative inside
"""
from .anatomy import Phantom, PhantomParams, make_phantom

__all__ = ["Phantom", "PhantomParams", "make_phantom"]
