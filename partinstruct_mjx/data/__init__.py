"""Demonstration storage: resumable per-run shards merged into robomimic-layout HDF5 files per category."""
