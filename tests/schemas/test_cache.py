"""The one cache root (schemas/cache.py): where it is by default, and that ``--cache`` wins."""

from pathlib import Path

from schemas.cache import CACHE_FOLDER_NAME, cache_root, default_cache_root, profiles_dir


def test_default_cache_root_follows_xdg_then_home(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_root() == tmp_path / "xdg" / CACHE_FOLDER_NAME
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/ignored")  # the XDG spec: relative paths are invalid
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_cache_root() == tmp_path / "home" / ".cache" / CACHE_FOLDER_NAME
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert default_cache_root() == tmp_path / "home" / ".cache" / CACHE_FOLDER_NAME
    assert default_cache_root().is_absolute()  # never the working directory


def test_given_cache_wins_and_profiles_live_under_it(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_root(tmp_path / "mine") == tmp_path / "mine"
    assert cache_root(None) == cache_root("") == tmp_path / "xdg" / CACHE_FOLDER_NAME
    assert profiles_dir(str(tmp_path / "mine")) == Path(tmp_path / "mine" / "profiles")


def test_no_module_spells_the_old_working_directory_cache():
    repo = Path(__file__).resolve().parents[2]
    old = "." + "cvvc-cache"
    offenders = [str(p.relative_to(repo)) for pkg in ("agent", "cvvc", "recordings", "schemas", "simulator_bridge",
                                                      "training") for p in (repo / pkg).rglob("*.py")
                 if old in p.read_text()]
    assert offenders == []


def _imports(path: Path) -> set[str]:
    import ast

    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
        elif isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
    return names


def test_path_helpers_need_no_sideways_import():
    """agent/ resolves a device map path through schemas; bridge_cli and cli of simulator_bridge are no circle."""
    repo = Path(__file__).resolve().parents[2]
    for p in (repo / "agent").rglob("*.py"):
        assert not any(m.startswith("simulator_bridge") for m in _imports(p)), p.name
    assert "simulator_bridge.bus.cli" not in _imports(repo / "simulator_bridge" / "bus" / "bridge_cli.py")
    assert "simulator_bridge.bus.cli" not in _imports(repo / "training" / "cli.py")
