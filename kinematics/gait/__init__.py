"""Gait reconstruction from marker trials: Plug-in-Gait, foot-to-hip chains, gait events, foot contact, inverse dynamics."""
