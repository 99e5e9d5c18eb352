"""diff4splat.io.structured: every decode error of a text, JSON or YAML file is one ValueError naming the file."""
import re

import pytest

from diff4splat.io.structured import read_json, read_text, read_yaml


def test_missing_file_is_file_not_found_naming_it(tmp_path):
    for reader in (read_text, read_json, read_yaml):
        with pytest.raises(FileNotFoundError, match=rf"^thing: {re.escape(str(tmp_path / 'x'))} not found$"):
            reader(tmp_path / "x", "thing")
    with pytest.raises(FileNotFoundError):  # a folder is not a file
        read_text(tmp_path, "thing")


def test_binary_file_names_the_first_bad_byte(tmp_path):
    path = tmp_path / "a.json"
    path.write_bytes(b'{"a": 1}\n\x89PNG')
    for reader in (read_text, read_json, read_yaml):
        with pytest.raises(ValueError, match=rf"^thing: {re.escape(str(path))} is not UTF-8 text \(byte 0x89 at "
                                             r"offset 9; a binary file\?\)$"):
            reader(path, "thing")


def test_invalid_json_gives_message_line_and_column(tmp_path):
    path = tmp_path / "c.json"
    path.write_text('{\n  "a": 1,\n  "b": }\n')
    with pytest.raises(ValueError, match=rf"^cfg: {re.escape(str(path))} is not valid JSON \(Expecting value at "
                                         r"line 3 column 8\)$"):
        read_json(path, "cfg")


def test_invalid_yaml_gives_problem_and_line(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("a: 1\nb: [1, 2\n")
    with pytest.raises(ValueError, match=rf"^cfg: {re.escape(str(path))} is not valid YAML \(.* at line \d+\)$"):
        read_yaml(path, "cfg")


@pytest.mark.parametrize(("text", "got"), [("[1, 2]", "list"), ('"s"', "string"), ("3", "number"), ("null", "null")])
def test_top_level_type_is_checked(tmp_path, text, got):
    path = tmp_path / "c.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=rf"must hold a JSON object, got a JSON {got}$"):
        read_json(path, "cfg")
    assert read_json(path, "cfg", expect=None) == __import__("json").loads(text)


def test_valid_files_parse_and_empty_yaml_is_an_empty_mapping(tmp_path):
    j, y, e = tmp_path / "a.json", tmp_path / "a.yaml", tmp_path / "e.yaml"
    j.write_text('{"x": [1, 2.5], "y": "é"}')
    y.write_text("x: [1, 2.5]\ny: é\n")
    e.write_text("")
    assert read_json(j, "a") == {"x": [1, 2.5], "y": "é"} == read_yaml(y, "a")
    assert read_yaml(e, "a") == {}
    with pytest.raises(ValueError, match="must hold a YAML list, got a YAML object"):
        read_yaml(y, "a", expect=list)


def test_yaml_reads_exponent_floats_without_a_dot_as_numbers(tmp_path):
    """PyYAML (YAML 1.1) read ``lr: 1e-4`` as the string '1e-4', and a training run crashed at its first step."""
    path = tmp_path / "stage.yaml"
    path.write_text("lr: 1e-4\nkl: -3E2\nsteps: 1000\nname: 1e-4x\nversion: '1e-4'\nbig: 1.5e+3\n")
    data = read_yaml(path, "stage")
    assert data == {"lr": 1e-4, "kl": -300.0, "steps": 1000, "name": "1e-4x", "version": "1e-4", "big": 1500.0}
    assert type(data["lr"]) is float and type(data["steps"]) is int
