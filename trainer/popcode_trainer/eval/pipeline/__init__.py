"""Models + a BOP split -> per-instance errors and scores: the steps ``popcode-train evaluate`` runs."""
