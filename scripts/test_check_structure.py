"""A test of scripts/check_structure.py itself: it plants each kind of problem in a scratch
workspace and sees the check find it (and pass the same tree without it), so a check that can no
longer fail is caught. Run by scripts/test.sh beside the check.

usage: python3 scripts/test_check_structure.py
"""
import os
import subprocess
import sys
import tempfile

CHECK = os.path.join(os.path.dirname(os.path.abspath(__file__)), "check_structure.py")


def workspace(files):
    """A scratch workspace of two crates (`alpha`, `beta/gamma`) holding `files` (path -> text)."""
    root = tempfile.mkdtemp(prefix="check-structure-")
    files = {"Cargo.toml": '[workspace]\nmembers = ["alpha", "beta/gamma"]\n', "alpha/src/lib.rs": "pub mod a;\n",
             "alpha/src/a.rs": "pub fn one() {}\n", "beta/gamma/src/lib.rs": "mod x;\nmod y;\n", **files}
    for path, text in files.items():
        os.makedirs(os.path.dirname(os.path.join(root, path)), exist_ok=True)
        with open(os.path.join(root, path), "w") as f:
            f.write(text)
    return root


def check(root):
    run = subprocess.run([sys.executable, CHECK, root], capture_output=True, text=True)
    return run.returncode, run.stdout


def wide_impl(methods, doc=""):
    fns = "".join(f"    pub fn m{i}(&self) {{}}\n" for i in range(methods))
    return f"pub struct S;\n\n{doc}impl S {{\n{fns}}}\n"


def test_a_clean_tree_passes():
    code, out = check(workspace({"beta/gamma/src/x.rs": "", "beta/gamma/src/y.rs": ""}))
    assert code == 0, out


def test_a_circle_in_any_member_is_found():
    root = workspace({"beta/gamma/src/x.rs": "use super::y::B;\npub struct A;\n",
                      "beta/gamma/src/y.rs": "use super::x::A;\npub struct B;\n"})
    code, out = check(root)
    assert code == 1 and "import loop in beta/gamma/: x <-> y" in out, out


def test_a_circle_through_crate_paths_is_found():
    root = workspace({"beta/gamma/src/x.rs": "pub fn f() { crate::y::g() }\n",
                      "beta/gamma/src/y.rs": "pub fn g() { crate::x::f() }\n"})
    code, out = check(root)
    assert code == 1 and "import loop in beta/gamma/" in out, out


def test_a_wide_impl_is_found_and_one_that_says_why_is_not():
    code, out = check(workspace({"alpha/src/a.rs": wide_impl(26)}))
    assert code == 1 and "impl S has 26 methods" in out, out
    code, out = check(workspace({"alpha/src/a.rs": wide_impl(25)}))
    assert code == 0, out
    code, out = check(workspace({"alpha/src/a.rs": wide_impl(26, "/// Wide because one table of verbs.\n")}))
    assert code == 0, out


def test_a_long_impl_is_found():
    body = "".join(f"        let _x{i} = {i};\n" for i in range(600))
    text = f"pub struct S;\n\nimpl S {{\n    pub fn f(&self) {{\n{body}    }}\n}}\n"
    code, out = check(workspace({"alpha/src/a.rs": text}))
    assert code == 1 and "impl S has 1 methods in 604 lines" in out, out


def test_a_long_function_is_found():
    body = "".join(f"    let _x{i} = {i};\n" for i in range(90))
    code, out = check(workspace({"alpha/src/a.rs": f"pub fn f() {{\n{body}}}\n"}))
    assert code == 1 and "fn f is 92 lines" in out, out


if __name__ == "__main__":
    tests = [v for k, v in sorted(globals().items()) if k.startswith("test_")]
    for t in tests:
        t()
    print(f"test_check_structure: {len(tests)} passed")
