"""Scans and rigs: what a user brings. Camera and projector models (scanner), pattern sets (patterns), frame
roles (roles), and the Scan with its native layout and `load_scan` (scan), the importers of the NeSS and procam
layouts (importers), the image and depth files (images), a scan's files read from inside its folder
(confinement) and ScanError (errors)."""
