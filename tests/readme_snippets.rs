//! The README's table-reading snippets run against the example folders in `results/examples/`:
//! every table a snippet reads is there, and each Python and SQL snippet runs on it and prints
//! something. A snippet reads `results/<study>/…` (the folder `kfmc run` writes); the test
//! points it at `results/examples/<study>/…`, the copy kept in the repository.
//!
//! The snippets use polars, pandas (pyarrow) and DuckDB, which `.ci/run` installs and there
//! sets KFMC_REQUIRE_INTEROP=1; elsewhere a snippet whose module is missing is skipped (the
//! tables are still checked).

mod common;

use common::repo;

/// Fenced code blocks of the README: (language, text).
fn code_blocks(readme: &str) -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut lang: Option<String> = None;
    let mut text = String::new();
    for line in readme.lines() {
        match (&lang, line.strip_prefix("```")) {
            (None, Some(l)) => {
                lang = Some(l.trim().to_string());
                text.clear();
            }
            (Some(l), Some(_)) => {
                out.push((l.clone(), std::mem::take(&mut text)));
                lang = None;
            }
            (Some(_), None) => {
                text.push_str(line);
                text.push('\n');
            }
            (None, None) => {}
        }
    }
    out
}

/// The `results/<study>/<table>.parquet` paths a snippet reads, as (study, table).
fn tables_read(snippet: &str) -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut rest = snippet;
    while let Some(i) = rest.find("results/") {
        let tail = &rest[i + "results/".len()..];
        let end = tail
            .find(|c: char| !(c.is_ascii_alphanumeric() || "_./-".contains(c)))
            .unwrap_or(tail.len());
        let path = &tail[..end];
        let parts: Vec<&str> = path.split('/').collect();
        if let [study, table] = parts[..]
            && let Some(t) = table.strip_suffix(".parquet")
        {
            out.push((study.to_string(), t.to_string()));
        }
        rest = &tail[end..];
    }
    out
}

fn python_has(modules: &str) -> bool {
    std::process::Command::new("python3")
        .args(["-c", &format!("import {modules}")])
        .stderr(std::process::Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// The Python modules a snippet imports (`import polars as pl` → polars).
fn imports(snippet: &str) -> Vec<String> {
    snippet
        .lines()
        .filter_map(|l| {
            let l = l.trim();
            let m = l
                .strip_prefix("import ")
                .or_else(|| l.strip_prefix("from "))?;
            Some(m.split([' ', ',', '.']).next()?.to_string())
        })
        .collect()
}

#[test]
fn readme_snippets_run_on_the_example_folders() {
    let readme = std::fs::read_to_string(repo().join("README.md")).unwrap();
    let examples = repo().join("results/examples");
    let required = std::env::var("KFMC_REQUIRE_INTEROP").is_ok();
    let mut snippets = 0;
    let mut ran = 0;
    for (lang, text) in code_blocks(&readme) {
        if lang != "python" && lang != "sql" {
            continue;
        }
        let reads = tables_read(&text);
        // Only snippets about a study kept in results/examples/.
        if reads.is_empty()
            || !reads
                .iter()
                .all(|(study, _)| examples.join(study).join("manifest.toml").exists())
        {
            continue;
        }
        snippets += 1;
        for (study, table) in &reads {
            let p = examples.join(study).join(format!("{table}.parquet"));
            assert!(
                p.exists(),
                "README snippet reads {table}.parquet of {study}; results/examples/{study}/ lacks it"
            );
        }
        let mut local = text.clone();
        for (study, _) in &reads {
            local = local.replace(
                &format!("results/{study}/"),
                &format!("{}/{study}/", examples.display()),
            );
        }
        let (modules, program) = if lang == "python" {
            (imports(&local), local)
        } else {
            // SQL snippets are DuckDB's; run them through its Python module.
            let query: String = local
                .lines()
                .filter(|l| !l.trim_start().starts_with("--"))
                .collect::<Vec<_>>()
                .join("\n");
            (
                vec!["duckdb".to_string()],
                format!(
                    "import duckdb\nrows = duckdb.sql({query:?}).fetchall()\nassert rows, 'no rows'\nprint(rows)\n"
                ),
            )
        };
        if !python_has(&modules.join(", ")) {
            assert!(
                !required,
                "KFMC_REQUIRE_INTEROP is set but one of {modules:?} is missing"
            );
            eprintln!(
                "skipped a {lang} snippet: pip install {}",
                modules.join(" ")
            );
            continue;
        }
        let o = std::process::Command::new("python3")
            .args(["-c", &program])
            .current_dir(repo())
            .output()
            .unwrap();
        assert!(
            o.status.success(),
            "README {lang} snippet failed:\n{program}\n{}",
            String::from_utf8_lossy(&o.stderr)
        );
        assert!(
            !o.stdout.is_empty(),
            "the snippet printed nothing:\n{program}"
        );
        ran += 1;
    }
    assert!(
        snippets >= 2,
        "found only {snippets} README snippets on example folders"
    );
    if required {
        assert_eq!(ran, snippets);
    }
}

#[test]
fn snippet_parsing_finds_paths_and_imports() {
    let s = "import polars as pl\nfrom pandas import x\ns = pl.read_parquet(\"results/a_b/runs.parquet\")\n-- 'results/c/steps.parquet'";
    assert_eq!(
        tables_read(s),
        [
            ("a_b".to_string(), "runs".to_string()),
            ("c".to_string(), "steps".to_string())
        ]
    );
    assert_eq!(imports(s), ["polars", "pandas"]);
    let blocks = code_blocks("x\n```python\na\n```\n```sql\nb\n```\n");
    assert_eq!(
        blocks,
        [
            ("python".to_string(), "a\n".to_string()),
            ("sql".to_string(), "b\n".to_string())
        ]
    );
}
