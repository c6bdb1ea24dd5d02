"""The base layer under `kinematics`, `phantoms` and `personalize`.

Bone and joint vocabulary (`bones`), the lower-limb topology (`topology`: the
coordinates, their names, signs and ranges, defined once), geometry helpers
(`geometry`), error types (`errors`) and atomic outputs (`atomic`).  It imports
none of the packages above it.
"""
