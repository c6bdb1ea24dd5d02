"""Gait reconstruction from marker trials: Plug-in-Gait, foot-to-hip chains, gait events, feet on force plates, foot contact, inverse dynamics."""
