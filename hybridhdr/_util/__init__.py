"""Shared private utilities every part may use: atomic writing of files and folders, TOML, input
checks, resource limits, prefetching, command-line argument types. Imports nothing above the core."""
