//! The catalogue of hostile specs in `tests/bad_specs/`: `kfmc validate` on each must exit 2
//! and print, on stderr, the file, the key path and the message that `expected.txt` gives,
//! and never a panic.

use std::path::{Path, PathBuf};
use std::process::Command;

struct Case {
    file: String,
    key_path: String,
    message: String,
}

fn dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/bad_specs")
}

fn cases() -> Vec<Case> {
    let text = std::fs::read_to_string(dir().join("expected.txt")).unwrap();
    text.lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .map(|l| {
            let parts: Vec<&str> = l.splitn(3, " | ").collect();
            assert_eq!(
                parts.len(),
                3,
                "expected.txt: `{l}` is not `file | key | message`"
            );
            Case {
                file: parts[0].trim().into(),
                key_path: parts[1].trim().into(),
                message: parts[2].trim().into(),
            }
        })
        .collect()
}

#[test]
fn every_bad_spec_is_refused_at_its_key_path_with_its_message() {
    let cases = cases();
    assert!(cases.len() >= 40, "only {} bad specs", cases.len());
    let mut files: Vec<String> = std::fs::read_dir(dir())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".toml"))
        .collect();
    files.sort();
    let mut listed: Vec<String> = cases.iter().map(|c| c.file.clone()).collect();
    listed.sort();
    assert_eq!(files, listed, "expected.txt and the .toml files disagree");

    let mut failures = Vec::new();
    for c in &cases {
        let path = dir().join(&c.file);
        let out = Command::new(env!("CARGO_BIN_EXE_kfmc"))
            .arg("validate")
            .arg(&path)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        // One problem per line: `  <file>: <key path>: <message>`, or `<file>: <message>`
        // when the TOML does not parse.
        let prefix = if c.key_path == "-" {
            format!("{}: ", path.display())
        } else {
            format!("{}: {}: ", path.display(), c.key_path)
        };
        let found = err.lines().any(|l| {
            l.trim_start()
                .strip_prefix(&prefix)
                .is_some_and(|rest| rest.contains(&c.message))
        });
        let code = out.status.code();
        if code != Some(2) || !found || err.contains("panicked") || !out.stdout.is_empty() {
            failures.push(format!(
                "{}: exit {code:?}, wanted `{prefix}…{}…`; stderr:\n{err}",
                c.file, c.message
            ));
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {} bad specs:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
}
