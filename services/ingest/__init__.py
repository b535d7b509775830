"""Ingest service: validation of raw sensor samples."""
