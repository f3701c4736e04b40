"""``popcode-train kit``: a user's models folder to a kit in the layout of the repository's ``models/``."""
