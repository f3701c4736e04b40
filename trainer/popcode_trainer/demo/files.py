"""The files of a demo's run folder, named once in a module that imports nothing: a tool that only reads a
finished run (``experiments.compare_demos``) need not load torch and the demo's steps to find them."""

REPORT_FILE = "report.md"
MODEL_CARD_FILE = "model_card.md"
SUMMARY_FILE = "summary.json"
SAMPLES_FILE = "samples.json"
