"""Files in and out: atomic writers for results (files.py); importers of recordings and
datasets and exporters of results land here. Imports geometry and session; no stage."""
