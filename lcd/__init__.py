"""Loop-closure detectors: SymbioLCD2 and its baselines (see the issue tracker for the plan)."""
