"""`python -m benchmarks regenerate --quick --out DIR`: every generated page of docs/results/
written into DIR, none empty, docs/results/ left alone; and docs/results/ holds the pages of
the generators and nothing else, so that the command regenerates every one of them."""

from __future__ import annotations

import pytest

from benchmarks.__main__ import GENERATORS, STAMP, main, stamp

from .conftest import ROOT

RESULTS = ROOT / "docs" / "results"


def test_the_quick_mode_writes_every_generated_page(regenerated):
    pages = [page for g in GENERATORS for page in g.pages]
    assert len(pages) == len(set(pages))  # no page written by two generators
    for page in pages:
        path = regenerated / page
        assert path.is_file() and path.stat().st_size > 0, page
        if page.endswith(".png"):
            assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", page
        else:
            text = path.read_text()
            assert text.startswith("# "), page  # a page with its title
            last = text.rstrip("\n").split("\n")[-1]  # and its date, command and host, once
            assert last.startswith(STAMP) and text.count(STAMP) == 1 and "--quick --only" in last, page
    assert sorted(p.name for p in regenerated.iterdir()) == sorted(pages)  # and nothing beside them


def test_docs_results_holds_every_generated_page_and_summaries_that_name_their_commands():
    """Every generated page is in docs/results/; a page there that no generator writes (a
    summary of several benchmarks' figures, kept by hand) names the commands it quotes."""
    pages = {page for g in GENERATORS for page in g.pages}
    present = {p.name for p in RESULTS.iterdir()}
    assert pages <= present
    for name in sorted(present - pages):
        assert name.endswith(".md"), name
        assert "python -m benchmarks." in (RESULTS / name).read_text(), name


def test_the_quick_mode_asks_for_a_folder_of_its_own(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["regenerate", "--quick"])
    assert exc.value.code == 2
    assert "--quick needs --out" in capsys.readouterr().err


def test_a_stamp_replaces_the_one_a_former_run_left(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("# A page\n\nfigures\n")
    stamp(page, "creep", 12.0, quick=False)
    stamp(page, "creep", 34.0, quick=False)
    text = page.read_text()
    assert text.count(STAMP) == 1 and "in 34 s" in text and text.startswith("# A page\n\nfigures\n\n")
    assert "regenerate --only creep`" in text  # the full run's command, without --quick
