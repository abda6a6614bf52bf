"""Store URLs with more than a host and a path (issue 25): a query (a token, a signature) goes with every request and
file names join the path; a fragment, a query on a bucket URL and a ':' inside a bucket name are refused in one line;
user info (``http://user:password@host``) is used for the requests but never written to a run's config.json, the
evaluation's result files or an error line. Served by the loopback server of test_remote_reads (127.0.0.1)."""

from __future__ import annotations

import shutil
import threading
from pathlib import Path

import pytest
from test_remote_reads import TOKEN, _Handler, _Server

from hoidata import store
from hoidata.errors import DataError, redact_urls

pytest.importorskip("aiohttp")
pytest.importorskip("fsspec")


@pytest.fixture(scope="module")
def served(tmp_path_factory, tiny_store_two_shards):
    """(base URL, request log) of a server holding the two-shard store as ``store``; its "token" mode wants
    ``?tok=...`` on every request, its "auth" mode alice's password."""
    root = tmp_path_factory.mktemp("urls")
    shutil.copytree(tiny_store_two_shards, root / "store")
    handler = type("Handler", (_Handler,), {"root": root, "stop": threading.Event(), "log": []})
    srv = _Server(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{srv.server_address[1]}", handler.log
    srv.shutdown()
    srv.server_close()
    thread.join(timeout=10)


def test_file_names_join_the_path_and_the_query_stays():
    where = store.resolve_store("https://h:8443/stores/dexycb/?sv=2024&sig=a%2Bb%3D")
    assert where.name == "dexycb" and where.base == "https://h:8443/stores/dexycb"
    joined = "https://h:8443/stores/dexycb/index.zarr/zarr.json?sv=2024&sig=a%2Bb%3D"
    assert where.file("index.zarr/zarr.json").url == joined
    assert where.file("shard-000000.tar").name == "shard-000000.tar"
    assert str(where) == "https://h:8443/stores/dexycb?sv=***&sig=***"  # a signature is a secret too


@pytest.mark.slow
def test_a_store_url_with_a_query_reads_as_its_folder(served, tiny_store_two_shards):
    from hoisdf.data.shards import store_shards

    base, log = served
    url = f"{base}/token/store?{TOKEN}"
    index, expected = store_shards(url)  # the index through zarr, the sizes, then every shard
    assert index.keys == store.read_index(tiny_store_two_shards).keys
    for source, (keys, size) in expected.items():
        assert [r["__key__"] for r in store.read_checked_shard(source, keys, size)] == list(keys)
    assert {method for method, mode, *_ in log if mode == "token"} == {"HEAD", "GET"}
    with pytest.raises(DataError, match="HTTP 403") as err:  # the same without its token: the server refuses
        store.read_index(f"{base}/token/store")
    assert str(err.value).startswith(f"{base}/token/store/index.zarr")


@pytest.mark.parametrize("url, problem", [
    ("http://host/stores/a#part", "cannot have a fragment"),
    ("https://host/a?x=1#", "cannot have a fragment"),
    ("s3://bucket/store?versionId=3", "a s3:// store URL takes no query"),
    ("gs://bucket:2/store", "not a store URL"),
    ("http://host:80x/store", "not a store URL"),
])
def test_a_url_the_reader_cannot_honour_is_refused_in_one_line(url, problem, mano_dir, tmp_path, capsys):
    from hoisdf.train import main as train

    with pytest.raises(DataError, match=problem):
        store.resolve_store(url)
    assert train(["--shards", url, "--mano", str(mano_dir), "--out", str(tmp_path / "run"), "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and problem in err[0] and not (tmp_path / "run").exists(), err


def test_a_store_weight_after_a_root_url_parses():
    from hoisdf.train import parse_store

    for text, path, weight in [("s3://bucket:2", "s3://bucket", 2.0), ("gs://bucket:0.5", "gs://bucket", 0.5),
                               ("s3://bucket", "s3://bucket", 1.0), ("http://host:8000:3", "http://host:8000", 3.0),
                               ("https://[::1]:8443/s:2", "https://[::1]:8443/s", 2.0),
                               ("http://host:8000", "http://host:8000", 1.0)]:
        spec = parse_store(text)
        assert (spec.path.url, spec.weight) == (path, weight), text
    with pytest.raises(DataError, match="weight"):
        parse_store("s3://bucket:0")


def test_redaction_masks_user_info_and_query_values_only():
    line = "error: http://alice:s3cr3t@host:81/s/x.tar?sig=abc&v=1: cannot read (see s3://bucket/a, /tmp/u@x)"
    masked = "error: http://***@host:81/s/x.tar?sig=***&v=***: cannot read (see s3://bucket/a, /tmp/u@x)"
    assert redact_urls(line) == masked
    error = DataError("https://tok@h/s", None, "http://u:pw@h/s: HTTP 401")  # the path and the problem
    assert str(error) == "https://***@h/s: http://***@h/s: HTTP 401"
    # a URL that Path() squashed into a folder name, a raw '@' in a password, a store's and a file's repr
    assert redact_urls("http:/u:pw@h/x?sig=1: not found") == "http:/***@h/x?sig=***: not found"
    assert redact_urls("see https://u:p@ss@h/x and C:/data/a@b") == "see https://***@h/x and C:/data/a@b"
    where = store.resolve_store("http://u:pw@h/s?sig=1")
    assert repr([where, where.file("a.tar")]) == ("[RemoteStore('http://***@h/s?sig=***'), "
                                                  "RemoteFile('http://***@h/s/a.tar?sig=***')]")


def test_every_command_line_parser_masks_urls_in_its_error_line(capsys):
    """argparse quotes the value it refuses: every parser of the project is cli_types.ArgumentParser, masking it."""
    import re

    from hoidata.cli_types import ArgumentParser

    root = Path(__file__).resolve().parents[1]
    files = [f for package in ("hoidata", "hoisdf") for f in sorted((root / package).rglob("*.py"))]
    plain = [str(f.relative_to(root)) for f in files if re.search(r"\bargparse\.ArgumentParser\(", f.read_text())]
    assert plain == [], f"parsers that print a refused URL as it is: {plain}"
    parser = ArgumentParser(prog="p")
    parser.add_argument("--n", type=int)
    with pytest.raises(SystemExit):
        parser.parse_args(["--n", "http://u:pw@h/x?sig=abc"])
    last = capsys.readouterr().err.splitlines()[-1]
    assert last == "p: error: argument --n: invalid int value: 'http://***@h/x?sig=***'"


def _every_file_text(folder: Path) -> str:
    return "\n".join(p.read_bytes().decode("latin-1") for p in sorted(folder.rglob("*")) if p.is_file())


SECRETS = ("s3cr3t", "alice", "SIGSECRET", "TOKSECRET")


@pytest.mark.slow
def test_a_url_password_never_reaches_config_results_or_error_lines(served, mano_dir, tmp_path, capfd, monkeypatch):
    """Every output of every command given a URL with a password and a signed query: stdout and stderr (progress
    bars on, captured at the file descriptors), every file under the folder the commands run in (a run's
    config.json, metrics.csv, tensorboard events, checkpoints; metrics.json and result files; verify's report,
    argparse's error lines, a URL squashed into a folder name by Path)."""
    from test_faults_train import TINY

    from hoidata.cli import main as hoidata
    from hoisdf.evaluate import main as evaluate
    from hoisdf.scoring.cli import main as score
    from hoisdf.train import main as train

    monkeypatch.chdir(tmp_path)  # a file written to the working folder is grepped too
    base, log = served
    url = base.replace("://", "://alice:s3cr3t@") + "/auth/store?X-Amz-Signature=SIGSECRET&token=TOKSECRET"
    run = tmp_path / "run"
    assert train(["--shards", url, "--val-shards", url, "--mano", str(mano_dir), "--out", str(run),
                  "--device", "cpu", *TINY, "train.max_steps=2", "train.val_every=1"]) == 0
    assert evaluate(["--ckpt", str(run), "--shards", url, "--mano", str(mano_dir), "--out", str(run / "eval"),
                     "--workers", "1", "--plausibility", "0", "--vis", "1"]) == 0
    assert any(mode == "auth" for _, mode, *_ in log)  # the password was sent (the server answers 401 without)
    assert "http://***@127.0.0.1" in _every_file_text(run)
    codes = [hoidata(["verify", url]), hoidata(["inspect", url, "--out", str(tmp_path / "grid.png")])]
    for bad in (url.replace("s3cr3t", "s3cr3tX"), url.replace("/store?", "/gone?")):  # a refused password, no store
        codes.append(train(["--shards", bad, "--mano", str(mano_dir), "--out", str(tmp_path / "bad")]))
    codes.append(train(["--shards", url, "--mano", url, "--out", str(tmp_path / "bad")]))  # Path squashes '//'
    codes.append(hoidata(["make-toy", "--out", url]))
    for argv, main in ((["--shards", url, "--mano", str(mano_dir), "--out", url], train),
                       (["--ckpt", str(run), "--shards", url, "--mano", str(mano_dir), "--out", url], evaluate),
                       ([url], score)):
        with pytest.raises(SystemExit) as exit_:  # argparse quotes the value it refuses
            main(argv)
        codes.append(exit_.value.code)
    assert codes == [1, 2, 2, 2, 2, 2, 2, 2, 2], codes
    out = capfd.readouterr()
    text = "\n".join([out.out, out.err, _every_file_text(tmp_path)])
    assert [s for s in SECRETS if s in text] == [], [line for line in text.splitlines() if "s3cr3t" in line]
    said = out.out + out.err  # each command named the URL, masked (verify on stdout, the others on stderr)
    assert said.count("http://***@127.0.0.1") >= 9 and "http:/***@127.0.0.1" in out.err, said
