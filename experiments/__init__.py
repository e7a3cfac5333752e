"""Experiments that reproduce the reference paper's results on the synthetic flume.

Run one with `python -m experiments NAME [--out DIR] [--full]`, all with `python -m experiments all`.
Each writes `table.md`, `table.csv` and PNG figures to `DIR/NAME/` (default `experiments/results`).
`--update-readme` splices the tables and figures into README.md's Results section.
"""
