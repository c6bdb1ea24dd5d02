"""Synthetic phantoms with exactly known anatomy (bones, landmarks, axes, joint frames).

Two kinds of anatomy:

* analytic (the default): `make_phantom` builds bones from signed distance functions;

  >>> from phantoms import make_phantom
  >>> ph = make_phantom(seed=0)
  >>> ph.sdf("femur_r", pts)       # signed distance, metres, negative inside

* real: `phantoms.real_anatomy.load_real_anatomy` takes a subject's bone meshes and an
  expert-built model of them as the truth skeleton, and `phantoms.real_subject.write_real_subject`
  writes its subject folder through any marker set (`kinematics.io.marker_sets`), lab
  (`phantoms.lab`) and body build (`phantoms.marker_placement`).
"""
from .anatomy import Phantom, PhantomParams, make_phantom

__all__ = ["Phantom", "PhantomParams", "make_phantom"]
