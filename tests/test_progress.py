"""Progress bars: drawn on a terminal, silent when stderr is a log file or a pipe (every command makes its
bars through cpdetect.progress)."""
import io

from batch_helpers import write_marker_images
from cpdetect.cli import main
from cpdetect.progress import bar, counter, iter_progress
from test_bad_input import GOOD_SURVEYED, _colmap_text


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_bars_draw_on_a_terminal_only(monkeypatch):
    for stream, drawn in ((io.StringIO(), False), (_Terminal(), True)):
        monkeypatch.setattr("sys.stderr", stream)
        assert list(iter_progress()(range(3), desc="work")) == [0, 1, 2]
        with counter(5, desc="count") as update:
            update(2, 5)
            update(5, 5)
        b = bar(total=2)
        b.close()
        text = stream.getvalue()
        assert (("work" in text) and ("count" in text)) == drawn, repr(text)
        assert bool(text) == drawn


def test_commands_write_no_bars_into_a_log(tmp_path, capsys):
    """stderr captured (not a TTY), as in a log file: only log lines, no bar redraws."""
    names = [f"{i:04d}.jpg" for i in range(4)]
    write_marker_images(tmp_path / "images", 4)
    (tmp_path / "gcps.csv").write_text(GOOD_SURVEYED)
    model = _colmap_text(tmp_path / "model", names)
    runs = [["detect", tmp_path / "images", "--out", tmp_path / "dets.json"],
            ["georef", "--reconstruction", model, "--images", tmp_path / "images", "--gcps", tmp_path / "gcps.csv",
             "--out", tmp_path / "out"]]
    for argv in runs:
        main([str(a) for a in argv])
        err = capsys.readouterr().err
        assert "\r" not in err and "%|" not in err and "image/s" not in err, (argv[0], err)
