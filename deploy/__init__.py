"""Scenarios, runners, metrics, figures and the ``omnifleet`` command line."""
