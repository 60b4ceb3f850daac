"""The whole chain: run (its stages and ledger), the quality verdict, the report, the demo."""
