"""Figures and self-contained HTML reports (presentation only: no estimates are computed here)."""
