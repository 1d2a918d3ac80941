"""Package data of the core: the paper's Table 1 robot (``paper_table1.toml``), the default robot file."""
