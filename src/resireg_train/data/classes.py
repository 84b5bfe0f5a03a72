"""Class-name files of the segmentation benchmarks (``conf/classes/<name>.txt``): one class per
line in label order, its names separated by commas; every name is prompted, and a pixel's score
for the class is its best-scoring name's (the synonyms rule of SCLIP's and NACLIP's
``configs/cls_*.txt`` and ``get_cls_idx``). The class's name in reports is its first name, or
the label before a colon (``background: sky, wall, ...``: VOC21's background is prompted by the
names of what it holds, never by the word). Lines starting with ``#`` are comments."""

from __future__ import annotations

from pathlib import Path

__all__ = ["class_file", "read_class_names"]


def class_file(value: str, key: str = "dataset.classes") -> Path:
    """The file ``value`` names: ``conf/classes/<value>.txt`` for a bare name, else the path
    itself (a ``.txt`` file of your own); a FileNotFoundError naming ``key`` and the files that
    exist when it is missing."""
    from resireg_train.config.paths import CONFIG_DIR

    folder = CONFIG_DIR / "classes"
    if value.endswith(".txt") or "/" in value:
        path = Path(value).expanduser()
    else:
        path = folder / f"{value}.txt"
    if not path.is_file():
        known = sorted(p.stem for p in folder.glob("*.txt"))
        raise FileNotFoundError(f"{key}={value!r}: no {path} (a name of conf/classes/: {known}, "
                                "or the path of a .txt file)")  # fmt: skip
    return path


def read_class_names(
    value: str, key: str = "dataset.classes"
) -> tuple[tuple[str, ...], tuple[tuple[str, ...], ...]]:
    """``(classes, names)`` of the file ``value`` names (:func:`class_file`): each class's
    label (its first name, or the text before a colon) and all its prompted names. An empty line between classes (it would shift every label
    after it), an empty name or an empty file is a ValueError naming the line."""
    path = class_file(value, key)
    lines = path.read_text(encoding="utf-8").splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    classes: list[str] = []
    names: list[tuple[str, ...]] = []
    for number, line in enumerate(lines, 1):
        if line.lstrip().startswith("#"):
            continue
        label, colon, prompted = line.partition(":")
        parts = tuple(part.strip() for part in (prompted if colon else line).split(","))
        if not line.strip() or not all(parts) or (colon and not label.strip()):
            raise ValueError(f"{key}={value!r}: {path} line {number} holds an empty class name "
                             f"({line!r}); one class per line, names separated by commas")  # fmt: skip
        classes.append(label.strip() if colon else parts[0])
        names.append(parts)
    if not names:
        raise ValueError(f"{key}={value!r}: {path} names no class")
    return tuple(classes), tuple(names)
