"""What produced a run, recorded in ``results.json``'s ``provenance`` block.

- :mod:`.code`: the code's git state (commit, branch, changed and untracked files, the diff);
- :mod:`.inputs`: the inputs' identities (datasets, models, exports, seeds, the command line);
- :mod:`.machine`: the machine (host, CPU, GPUs, package versions, CPU time);
- :mod:`.block`: the settings (``provenance.*``) and the block that joins them at a run's start
  and end, and an export's ``provenance.json``.

Imported by the run record, the training CLI (an export's provenance) and the run tools (the
index, rerun's drift); imports ``resireg`` and the config ground only.
"""
