"""The ECCV 2002 paper's experiments, reproduced (one module per experiment; see experiments/)."""
