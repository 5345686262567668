"""The README's two commands stay in sync with CI and never pull CUDA wheels."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    return re.findall(r"```bash\n(.+?)\n```", text)[:2]


def test_readme_starts_with_the_two_commands():
    main_job, tests = readme_commands()
    assert "facenormals reconstruct examples/data/astronaut.jpg" in main_job and "python -m pytest" in tests
    for command in (main_job, tests):
        # torch is pinned to the local CPU build before the package, so pip never resolves CUDA wheels
        assert command.index("pip install -q torch==2.13.0") < command.index("pip install -q -e ")


def test_ci_runs_the_readme_test_command():
    assert readme_commands()[1] in (ROOT / ".ci" / "run").read_text()


def test_the_main_job_photo_is_bundled():
    main_job = readme_commands()[0]
    photo = re.search(r"facenormals reconstruct (\S+)", main_job).group(1)
    assert (ROOT / photo).is_file()
