"""The end-to-end demo (``popcode-train demo``): its steps (render -> train -> export), the epoch budget, the
run itself and its report."""
