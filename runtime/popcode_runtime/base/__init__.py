"""The base: errors, argument checks, bounded JSON reading and atomic file writes. Imports nothing of popcode."""
