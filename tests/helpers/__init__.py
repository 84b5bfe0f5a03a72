"""The test suite's shared helpers, one module per thing they provide (``tests/`` is on the
path: ``pythonpath`` in pyproject's ``[tool.pytest.ini_options]``, and ``PYTHONPATH`` for the
runs a test starts that load a callback from here), imported as ``from helpers.run import run``:

- ``paths``: ``TESTS`` and ``ROOT``, the suite's folder and the checkout, for a test at any depth;
- ``run``: the console scripts in a fresh process as a user runs them, and ``started``, the one
  way a test starts a long-lived process (killed with its group when the test ends);
- ``tiny``: the tiny model parts of ``experiment=smoke``, read from ``conf/model/``;
- ``sweeps``: a sweep job's folder as Hydra and ``run_task`` leave it (report tests);
- ``fake_hubs``: fake torch.hub repositories of the encoder zoo, one module per upstream repo;
- ``sam``: a tiny random SAM 2 saved in transformers' format (also a script);
- ``ovss8_fixtures``, ``posed3d_fixtures``: tiny benchmark folders in their downloaded layouts;
- ``ade20k``: tiny ADE20K validation folders, clean or with one sample of each fault;
- ``wandb_log``: the records of W&B's offline run file, read by hand;
- ``ros2``: Fast DDS on shared memory, a spinning executor, the no-UDP check;
- ``postgres``: a PostgreSQL server of a test's own;
- ``optional``: optional references whose import can fail for other reasons (open3d);
- ``ddp``, ``faults``, ``hold``: Lightning callbacks loaded into real runs by ``_target_``
  (``helpers.ddp.SeenCaptions``, ``helpers.faults.SigintAt``, ``helpers.hold.WaitFor``);
- ``fake_srun``: a stand-in for SLURM's ``srun`` started by path (a script).

Test files import helpers, never each other across folders; this package is the one place for
what several test files share (``tests/project/test_layout.py`` checks it).
"""
