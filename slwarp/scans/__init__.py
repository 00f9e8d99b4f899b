"""Scans and rigs: what a user brings. Camera and projector models (scanner), pattern sets (patterns), frame
roles (roles), and the Scan with its on-disk layouts and importers (scan)."""
