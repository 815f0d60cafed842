"""Offline training: labelled recordings -> models (single action, banks, transitions)."""
