"""The reports of the benchmark suites: base.py (what every report shares), scores.py and training.py (the report of
a suite of returns), and one module per suite family, which a suite names in suites.py (Suite.report).

A family's module has:
- ORDER: where its suites stand in the READMEs' Results blocks (by ORDER, then by folder name);
- write_report(folder, runs, reference, results): writes <folder>/report.md and its curves, and returns the markdown;
- readme_lines(folder, results, reference, full): the folder's lines in a Results block, benchmarks/README.md's when
  `full`, else README.md's ([] for none).
"""
