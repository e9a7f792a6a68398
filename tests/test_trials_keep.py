"""``labctl trials --keep failures``: the records of the trials that went wrong stay, the others' go; every
result stays in results.jsonl and the report links only records that exist."""

from __future__ import annotations

import json
import re
import shutil

from fakes import run_cli

from labctl.workspace import sample_lab_path


def test_keep_failures_keeps_only_the_failed_trials_records(tmp_path, capsys):
    lab = tmp_path / "lab"
    shutil.copytree(sample_lab_path(), lab, ignore=shutil.ignore_patterns("runs"))
    text = (lab / "lab.yaml").read_text()
    # a time-out just at the sample lab's time to identity (about 3.0-3.3 s): some trials make it, some do not
    (lab / "lab.yaml").write_text(re.sub(r"(?m)^(  timeout_s:).*$", r"\1 3.05", text))
    code, out, err = run_cli(capsys, "--lab", str(lab), "--json", "trials", "--n", "4", "--speed", "8",
                             "--keep", "failures", "--jobs", "1")
    assert code == 0, err
    s = json.loads(out)
    failed = {t["index"] for t in s["trials"] if not t["correct"]}
    assert failed and len(failed) < 4  # both kinds, or the test shows nothing
    folder = lab / "runs" / s["sweep"].split("/")[-1]
    kept = sorted(p.name for p in (folder / "trials").iterdir())
    assert kept == sorted(f"{i:05d}-seed{i}" for i in failed)
    for t in s["trials"]:
        assert (t["record"] is None) == t["correct"]
        rec = folder / "trials" / f"{t['index']:05d}-seed{t['index']}"
        assert t["record"] is None or (rec / "events.jsonl").is_file()
    lines = [json.loads(x) for x in (folder / "results.jsonl").read_text().splitlines()]
    assert len(lines) == 4  # every result stays
    page = (folder / "report.html").read_text()
    links = re.findall(r'href="(trials/[^"]+)/report.html"', page)
    assert sorted(links) == [f"trials/{k}" for k in kept]
    assert json.loads((folder / "spec.json").read_text())["keep"] == "failures"
