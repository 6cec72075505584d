"""Shared pieces of the paper-reproduction experiments, one module per job:

- :mod:`.paper`: the paper's numbers and the soil model;
- :mod:`.scenery`: the shared camera set-up and terrain;
- :mod:`.runs`: quick/full set-up, command line, logging, summaries;
- :mod:`.records`: rendering, measuring, per-frame CSV and errors (:mod:`sinkjax.metrics`);
- :mod:`.report`: Markdown tables and figures;
- :mod:`.stages`: the soft method stage by stage, each stage compiled alone and timed.
"""
