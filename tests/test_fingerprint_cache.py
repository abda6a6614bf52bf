"""The build's input stamps hash a file once per size and mtime in a process (HOT3D: every record of a clip reads
the clip's tar, which was hashed again for each record), and hash it again when it changes."""

from __future__ import annotations

import os
from types import SimpleNamespace

from hoidata.records import fingerprint


def test_a_file_read_by_many_frames_is_hashed_once_until_it_changes(tmp_path, monkeypatch):
    calls = []
    real = fingerprint.file_sha256
    monkeypatch.setattr(fingerprint, "file_sha256", lambda path: calls.append(path) or real(path))
    clip = tmp_path / "clip-000001.tar"
    clip.write_bytes(b"a" * 1000)
    frame = SimpleNamespace(image=None, image_path=clip, segmentation_path=None)
    stamps = [fingerprint.frame_inputs(frame, tmp_path) for _ in range(5)]
    assert len(calls) == 1
    assert all(s == stamps[0] for s in stamps) and stamps[0]["clip-000001.tar"][2] == real(clip)
    clip.write_bytes(b"b" * 1001)  # another size: hashed again
    assert fingerprint.frame_inputs(frame, tmp_path)["clip-000001.tar"][2] == real(clip) != stamps[0][
        "clip-000001.tar"][2]
    clip.write_bytes(b"c" * 1001)  # same size, another mtime: hashed again
    os.utime(clip, ns=(1, 2))
    assert fingerprint.frame_inputs(frame, tmp_path)["clip-000001.tar"][2] == real(clip)
    assert len(calls) == 3
