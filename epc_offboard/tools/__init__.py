"""Tools around the product: the sim demo, comparisons, benchmarks, figures, exporters, the db
command.
"""
