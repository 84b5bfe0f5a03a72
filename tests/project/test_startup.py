"""The entry points answer --help, --cfg job and a bad config value before the heavy
libraries load: their modules import neither torch nor Lightning (README, "Start-up")."""

import subprocess
import sys


def test_entry_point_modules_import_no_heavy_library():
    code = (
        "import sys\n"
        "import resireg_train.cli.train, resireg_train.cli.eval, resireg_train.cli.report\n"
        "import resireg_train.checks.eval, resireg_train.checks.train, resireg_train.record.run_record, resireg.specs.variants\n"
        "import resireg_train.cli.playground, resireg_train.playground.examples\n"
        "import resireg_train.cli.map\n"
        "heavy = ('torch', 'lightning', 'open_clip', 'timm', 'datasets', 'pandas', 'matplotlib',\n"
        "         'gradio', 'skimage', 'rosbags', 'rerun')\n"
        "print(sorted(m for m in heavy if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_a_bad_value_is_reported_without_loading_torch(tmp_path):
    code = (
        "import sys\n"
        "from hydra import compose, initialize_config_dir\n"
        "from resireg_train.cli.job import CONFIG_DIR\n"
        "from resireg.errors import ConfigError\n"
        "from resireg_train.checks.train import validate\n"
        "with initialize_config_dir(str(CONFIG_DIR), version_base='1.3'):\n"
        "    cfg = compose('train', overrides=['experiment=smoke', 'model.optimizer.lr=-1'])\n"
        "try:\n"
        "    validate(cfg)\n"
        "except ConfigError as err:\n"
        "    print('torch' in sys.modules, 'model.optimizer.lr=-1' in str(err))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False True", out.stdout + out.stderr


def test_playground_answers_help_and_bad_arguments_before_torch_and_gradio():
    code = (
        "import sys\n"
        "from resireg_train.cli.playground import main\n"
        "for argv in (['--help'], [], ['--encoder', 'tiny', '--port', '70000'],\n"
        "             ['--encoder', 'nope'], ['--encoder', 'resireg_vlm']):\n"
        "    try:\n"
        "        main(argv)\n"
        "    except SystemExit as exit:\n"
        "        print(exit.code)\n"
        "print(sorted(m for m in ('torch', 'gradio') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.splitlines()[-6:] == ["0", "2", "2", "2", "2", "[]"], out.stdout + out.stderr
    assert "--port=70000: expected 1..65535" in out.stderr
    assert "--encoder='nope': no such config" in out.stderr and "'clip_vit_b16'" in out.stderr
    assert "--model-path is required with --encoder='resireg_vlm'" in out.stderr


def test_late_source_checks_answer_before_torch_loads(tmp_path):
    """Issue 22, case 12: a model_path, model.init_from or --model-path that names no export
    (or checkpoint) is reported by the config check, with torch never imported (it took 7-10 s,
    after the model was built)."""
    code = (
        "import sys\n"
        "script, *sys.argv[1:] = sys.argv[1:]\n"
        "module = {'eval': 'resireg_train.cli.eval', 'train': 'resireg_train.cli.train',\n"
        "          'playground': 'resireg_train.cli.playground'}[script]\n"
        "main = __import__(module, fromlist=['main']).main\n"
        "try:\n"
        "    main()\n"
        "except SystemExit as exit:\n"
        "    print('exit', exit.code, 'torch' in sys.modules)\n"
    )
    empty = tmp_path / "empty"
    empty.mkdir()
    cases = {
        "eval": (["model_path=/nope", "dataset=synthetic"],
                 "model_path='/nope': '/nope' is not an export folder (and not a Hugging Face "
                 "repo id 'owner/name')"),
        "train": (["experiment=smoke", "+model.init_from=/nope"],
                  "model.init_from='/nope': no such file or folder: expected a training "
                  "checkpoint (<run>/checkpoints/last.ckpt) or an export folder (<run>/export)"),
        "playground": (["--model-path", str(empty)],
                       f"--model-path: '{empty}' holds no config.json (not a ResiregVLM export)"),
    }  # fmt: skip
    for script, (args, expected) in cases.items():
        if script != "playground":
            args = [*args, f"hydra.run.dir={tmp_path / script}"]
        out = subprocess.run([sys.executable, "-c", code, script, *args], capture_output=True,
                             text=True, timeout=120)  # fmt: skip
        assert out.stdout.splitlines()[-1] in ("exit 1 False", "exit 2 False"), out.stdout
        assert expected in out.stderr, (script, out.stderr[-2000:])
