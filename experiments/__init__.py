"""experiments: orchestration (CLI, demo, benchmarks, paper reproduction, tournaments). No math here."""
