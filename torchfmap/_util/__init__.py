"""Shared helpers of every layer: input checks, files, threads, lazy imports, progress."""
