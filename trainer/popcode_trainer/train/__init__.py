"""Training: the typed config, the network, the output representations and their losses, the training sets
built from BOP splits, and the resumable (optionally distributed) training loop that writes a run folder."""
