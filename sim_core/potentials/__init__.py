"""Energy terms of the incremental potential: one module per potential (see base.py)."""
