"""sequences.documents.load_document: one-line InputErrors naming the file for every way a read fails."""

import pytest

from sequences.documents import load_document
from sequences.errors import InputError


def test_parses_yaml_by_suffix_and_json_otherwise(tmp_path):
    (tmp_path / "a.yaml").write_text("x: [1, 2]\n")
    (tmp_path / "a.json").write_text('{"x": [1, 2]}')
    (tmp_path / "a.txt").write_text("x: 3\n")
    assert load_document(tmp_path / "a.yaml", "doc") == {"x": [1, 2]}
    assert load_document(tmp_path / "a.json", "doc") == {"x": [1, 2]}
    assert load_document(tmp_path / "a.txt", "doc", as_yaml=True) == {"x": 3}


@pytest.mark.parametrize("name, text, message", [
    ("bad.yaml", "x: [1, 2\n", "malformed YAML"),
    ("bad.json", '{"x": ', "malformed JSON"),
    ("bin.json", b"\xff\xfe\x00", "cannot read doc (UnicodeDecodeError)"),
])
def test_malformed_or_unreadable_documents_are_one_line_errors(tmp_path, name, text, message):
    path = tmp_path / name
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(InputError) as info:
        load_document(path, "doc")
    assert message in str(info.value) and str(path) in str(info.value) and "\n" not in str(info.value)


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(InputError, match="doc not found"):
        load_document(tmp_path / "none.yaml", "doc")
    with pytest.raises(InputError, match="no such thing"):
        load_document(tmp_path / "none.yaml", "doc", missing="no such thing")
    with pytest.raises(InputError, match=r"cannot read doc \(IsADirectoryError\)"):
        load_document(tmp_path, "doc")
