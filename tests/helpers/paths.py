"""Where the suite lives: ``TESTS`` (this ``tests/`` folder, with its data, fixtures and
test-only ``conf/``) and ``ROOT`` (the project checkout above it), the one source of both for
test files at any depth of the mirrored tree."""

from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]
ROOT = TESTS.parent
