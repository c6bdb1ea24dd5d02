"""Evaluation against known truth: truth comparison, phantom and realistic validation, the demo."""
