"""Utilities every command line uses: files (atomic writes, --out guard, lock), signals, checks."""
