"""resireg.secrets: URL passwords masked, URLs found in free text, secret files
named, against hand-written expectations."""

import logging

import pytest

from resireg.secrets import SecretFilter, looks_secret, mask_text, mask_url


@pytest.mark.parametrize(
    ("url", "masked"),
    [
        ("http://user:password@host:5000", "http://user:***@host:5000"),
        ("http://user:p%40ss@host:5000/api?x=1", "http://user:***@host:5000/api?x=1"),
        (
            "postgresql+psycopg://u:s3cret@db:5432/optuna",
            "postgresql+psycopg://u:***@db:5432/optuna",
        ),
        ("https://h/x?token=abc&b=1", "https://h/x?token=***&b=1"),
        ("https://h/x?PASSWORD=abc", "https://h/x?PASSWORD=***"),
        ("http://host:5000", "http://host:5000"),
        ("http://user@host/", "http://user@host/"),
        ("sqlite:////tmp/mlflow.db", "sqlite:////tmp/mlflow.db"),
        ("outputs/mlflow.db", "outputs/mlflow.db"),
    ],
)
def test_a_urls_password_and_credential_parameters_are_masked(url, masked):
    assert mask_url(url) == masked


def test_urls_inside_a_command_line_are_masked_and_the_rest_kept():
    line = (
        "resireg-train tracker=mlflow tracker.mlflow.tracking_uri=http://ann:hunter2@h:5000 "
        "'hparams_search.storage=postgresql+psycopg://bo:pw@db/x' seed=3"
    )
    assert mask_text(line) == (
        "resireg-train tracker=mlflow tracker.mlflow.tracking_uri=http://ann:***@h:5000 "
        "'hparams_search.storage=postgresql+psycopg://bo:***@db/x' seed=3"
    )


@pytest.mark.parametrize(
    ("path", "secret"),
    [
        (".env", True),
        (".env.local", True),
        ("notes/token.txt", True),
        (".aws/credentials", True),
        ("deploy/server.PEM", True),
        ("home/.ssh/id_ed25519", True),
        ("src/my_callback.py", False),
        ("data/big.bin", False),
        ("monkey.py", False),
    ],
)
def test_secret_files_are_named_by_any_part_of_their_path(path, secret):
    assert looks_secret(path) is secret


def test_the_logging_filter_masks_a_formatted_message(caplog):
    log = logging.getLogger("resireg.test.secrets")
    log.addFilter(SecretFilter())
    with caplog.at_level(logging.INFO, logger="resireg.test.secrets"):
        log.info("tracking to %s", "http://u:topsecret@h:1")
    assert caplog.messages == ["tracking to http://u:***@h:1"]
    assert "topsecret" not in caplog.text
