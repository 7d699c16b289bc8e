"""sequences.documents.load_document: one-line InputErrors naming the file for every way a read fails."""

import pytest

from sequences.documents import load_document, load_mapping
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


def test_load_mapping_checks_shape_and_keys(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("")
    assert load_mapping(path, "camera", ("fx", "fy")) == {}
    path.write_text("fx: 500\n")
    assert load_mapping(path, "camera", ("fx", "fy")) == {"fx": 500}
    path.write_text("- 1\n")
    with pytest.raises(InputError, match=r"c\.yaml: camera must be a mapping of fx, fy"):
        load_mapping(path, "camera", ("fx", "fy"))
    path.write_text("fx: 1\nfocal: 2\n")
    with pytest.raises(InputError, match=r"unknown camera keys \['focal'\]; expected \['fx', 'fy'\]"):
        load_mapping(path, "camera", ("fx", "fy"))
    with pytest.raises(InputError, match="camera file not found"):
        load_mapping(tmp_path / "none.yaml", "camera", ("fx",))
