//! The documentation is tested: README.md and every page of the book in `docs/src/`.
//!
//! * Table-reading snippets (Python and SQL) run against the example folders in
//!   `results/examples/`: every table a snippet reads is there, and each snippet runs on it
//!   and prints something. A snippet reads `results/<study>/…` (the folder `kfmc run`
//!   writes); the test points it at `results/examples/<study>/…`, the copy kept in the
//!   repository. The snippets use polars, pandas (pyarrow) and DuckDB, which `.ci/run`
//!   installs and there sets KFMC_REQUIRE_INTEROP=1; elsewhere a snippet whose module is
//!   missing is skipped.
//! * Every TOML block that is a whole spec (it has a `[model]` table) passes `kfmc validate`.
//! * Command blocks marked for it run: a `sh`, `bash` or `console` block right after a line
//!   `<!-- test -->` (or `<!-- test: ARGS -->`) has each of its `kfmc …` and
//!   `cargo run --release -- …` lines (in a console block, the lines after `$ `) run in a
//!   scratch folder that sees the repository's `experiments/` and `examples/`, in order, and
//!   each must exit 0; in a `yaml` block (a CI job) the commands are the `- run:` lines; the
//!   `python3 …` lines of a yaml, sh or bash block run too (they need the interop packages:
//!   the block stops there without them unless KFMC_REQUIRE_INTEROP is set). ARGS (e.g. `--runs 5`) are added to the commands that run a study
//!   (`run`, `check`, `simulate`, `power`, `tune`), replacing the command's own value of the
//!   same flag, so the test stays small. The comment is
//!   invisible in the rendered book.
//! * Every relative link and image resolves to a file of the repository, and every `#anchor`
//!   into a page to one of its headings (as mdBook writes their ids); every page of
//!   `docs/src/` is in `SUMMARY.md`; the README stays a front page (at most 300 lines).
//! * The column list of `docs/src/reference/tables.md` is generated from
//!   `kfmc::output::schema`; `KFMC_BLESS=1` rewrites it.

use crate::common::repo;

/// Fenced code blocks of a Markdown text: (language, text).
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
    let examples = repo().join("results/examples");
    let required = std::env::var("KFMC_REQUIRE_INTEROP").is_ok();
    let mut snippets = 0;
    let mut ran = 0;
    let blocks = doc_pages()
        .iter()
        .flat_map(|p| code_blocks(&std::fs::read_to_string(p).unwrap()))
        .collect::<Vec<_>>();
    for (lang, text) in blocks {
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
                "a documentation snippet reads {table}.parquet of {study}; results/examples/{study}/ lacks it"
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
            "documentation {lang} snippet failed:\n{program}\n{}",
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
        "found only {snippets} documentation snippets on example folders"
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

/// README.md and every Markdown page under `docs/src/`, sorted.
fn doc_pages() -> Vec<std::path::PathBuf> {
    fn walk(dir: &std::path::Path, out: &mut Vec<std::path::PathBuf>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(&p, out);
            } else if p.extension().is_some_and(|x| x == "md") {
                out.push(p);
            }
        }
    }
    let mut out = vec![repo().join("README.md")];
    walk(&repo().join("docs/src"), &mut out);
    out.sort();
    out
}

fn rel(p: &std::path::Path) -> String {
    p.strip_prefix(repo()).unwrap_or(p).display().to_string()
}

/// Markdown with fenced blocks and inline code blanked out, so that links are only read from
/// prose (a `](x)` inside code is not a link).
fn prose(text: &str) -> String {
    let mut out = String::new();
    let mut fence = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            fence = !fence;
            out.push('\n');
            continue;
        }
        if fence {
            out.push('\n');
            continue;
        }
        let mut in_code = false;
        for c in line.chars() {
            if c == '`' {
                in_code = !in_code;
            }
            out.push(if in_code || c == '`' { ' ' } else { c });
        }
        out.push('\n');
    }
    out
}

/// The targets of Markdown links and images, `[text](target)` and `![alt](target)`, and of
/// `src="…"`/`href="…"` attributes.
fn link_targets(text: &str) -> Vec<String> {
    let text = prose(text);
    let mut out = Vec::new();
    let mut rest = text.as_str();
    while let Some(i) = rest.find("](") {
        let tail = &rest[i + 2..];
        let end = tail.find([')', ' ', '\n']).unwrap_or(tail.len());
        out.push(tail[..end].to_string());
        rest = &tail[end..];
    }
    for attr in ["src=\"", "href=\""] {
        let mut rest = text.as_str();
        while let Some(i) = rest.find(attr) {
            let tail = &rest[i + attr.len()..];
            let end = tail.find('"').unwrap_or(tail.len());
            out.push(tail[..end].to_string());
            rest = &tail[end..];
        }
    }
    out
}

/// The ids mdBook gives a page's headings: lower case, spaces to `-`, only alphanumerics,
/// `-` and `_` kept; a repeated id gets `-1`, `-2`, ….
fn heading_ids(text: &str) -> Vec<String> {
    let mut ids: Vec<String> = Vec::new();
    let mut fence = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            fence = !fence;
        }
        if fence || !line.starts_with('#') {
            continue;
        }
        let title = line.trim_start_matches('#').trim();
        let base: String = title
            .chars()
            .filter_map(|c| {
                if c.is_whitespace() {
                    Some('-')
                } else if c.is_alphanumeric() || c == '-' || c == '_' {
                    Some(c.to_lowercase().next().unwrap())
                } else {
                    None
                }
            })
            .collect();
        let mut id = base.clone();
        let mut k = 1;
        while ids.contains(&id) {
            id = format!("{base}-{k}");
            k += 1;
        }
        ids.push(id);
    }
    ids
}

#[test]
fn every_relative_link_of_the_docs_resolves() {
    let mut broken = Vec::new();
    let mut checked = 0;
    for page in doc_pages() {
        let text = std::fs::read_to_string(&page).unwrap();
        for target in link_targets(&text) {
            if target.contains("://") || target.starts_with("mailto:") || target.is_empty() {
                continue;
            }
            checked += 1;
            let (path, anchor) = match target.split_once('#') {
                Some((p, a)) => (p, Some(a)),
                None => (target.as_str(), None),
            };
            let file = if path.is_empty() {
                page.clone()
            } else {
                page.parent().unwrap().join(path)
            };
            if !file.exists() {
                broken.push(format!("{}: {target}: no such file", rel(&page)));
                continue;
            }
            if let Some(a) = anchor
                && file.extension().is_some_and(|x| x == "md")
            {
                let ids = heading_ids(&std::fs::read_to_string(&file).unwrap());
                if !ids.iter().any(|id| id == a) {
                    broken.push(format!(
                        "{}: {target}: no heading with id `{a}` in {}",
                        rel(&page),
                        rel(&file)
                    ));
                }
            }
        }
    }
    assert!(broken.is_empty(), "broken links:\n{}", broken.join("\n"));
    assert!(
        checked > 50,
        "only {checked} links found: is the parser broken?"
    );
}

#[test]
fn every_page_is_in_the_summary_and_the_readme_is_a_front_page() {
    let src = repo().join("docs/src");
    let summary = std::fs::read_to_string(src.join("SUMMARY.md")).unwrap();
    let listed = link_targets(&summary);
    let missing: Vec<String> = doc_pages()
        .iter()
        .filter(|p| p.starts_with(&src) && !p.ends_with("SUMMARY.md"))
        .map(|p| p.strip_prefix(&src).unwrap().display().to_string())
        .filter(|p| !listed.contains(p))
        .collect();
    assert!(
        missing.is_empty(),
        "pages mdBook would not render (not in SUMMARY.md): {missing:?}"
    );
    let readme = std::fs::read_to_string(repo().join("README.md")).unwrap();
    let lines = readme.lines().count();
    assert!(
        lines <= 300,
        "README.md has {lines} lines; the detail belongs in docs/"
    );
    // The README's two set-up commands, exactly.
    for cmd in [
        "cargo run --release -- run experiments/planar_seed_study.toml",
        "cargo test --release",
    ] {
        assert!(readme.contains(cmd), "README.md lacks `{cmd}`");
    }
}

/// A TOML block is a whole spec when it has a `[model]` table; other blocks are fragments.
#[test]
fn every_spec_in_the_docs_validates() {
    let dir = tempfile::tempdir().unwrap();
    let mut specs = 0;
    for page in doc_pages() {
        let text = std::fs::read_to_string(&page).unwrap();
        for (i, (lang, block)) in code_blocks(&text).into_iter().enumerate() {
            if lang != "toml" || !block.lines().any(|l| l.trim() == "[model]") {
                continue;
            }
            specs += 1;
            let spec = dir.path().join(format!("spec{specs}.toml"));
            std::fs::write(&spec, &block).unwrap();
            let o = crate::common::kfmc()
                .arg("validate")
                .arg(&spec)
                .current_dir(dir.path())
                .output()
                .unwrap();
            assert!(
                o.status.success(),
                "{}, code block {}: the spec does not validate:\n{block}\n{}",
                rel(&page),
                i + 1,
                String::from_utf8_lossy(&o.stderr)
            );
        }
    }
    assert!(specs >= 3, "found only {specs} whole specs in the docs");
}

/// The `kfmc` command lines of a block: `kfmc …` and `cargo run --release -- …` lines (after
/// `$ ` in a console block), without trailing comments, as argument lists.
fn command_lines(lang: &str, block: &str) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    for line in block.lines() {
        let line = match lang {
            "console" => match line.strip_prefix("$ ") {
                Some(l) => l,
                None => continue,
            },
            "yaml" => match line.trim().strip_prefix("- run: ") {
                Some(l) => l,
                None => continue,
            },
            _ => line,
        };
        let line = line.split(" #").next().unwrap().trim();
        let args = if let Some(a) = line.strip_prefix("kfmc ") {
            a
        } else if let Some(a) = line.strip_prefix("cargo run --release -- ") {
            a
        } else if lang != "console" && line.starts_with("python3 ") {
            out.push(line.split_whitespace().map(str::to_string).collect());
            continue;
        } else {
            continue;
        };
        out.push(args.split_whitespace().map(str::to_string).collect());
    }
    out
}

/// Whether `python3` can import what the documented Python commands use; with
/// KFMC_REQUIRE_INTEROP set it must.
fn python_ready() -> bool {
    let ok = std::process::Command::new("python3")
        .args(["-c", "import numpy, polars, pyarrow, filterpy"])
        .output()
        .is_ok_and(|o| o.status.success());
    assert!(
        ok || std::env::var_os("KFMC_REQUIRE_INTEROP").is_none(),
        "KFMC_REQUIRE_INTEROP is set but python3 cannot import numpy, polars, pyarrow, filterpy"
    );
    ok
}

#[test]
fn marked_command_blocks_run() {
    let mut blocks = 0;
    let mut commands = 0;
    for page in doc_pages() {
        let text = std::fs::read_to_string(&page).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        for (i, line) in lines.iter().enumerate() {
            let Some(marker) = line
                .trim()
                .strip_prefix("<!-- test")
                .and_then(|m| m.strip_suffix("-->"))
            else {
                continue;
            };
            let extra: Vec<String> = marker
                .trim()
                .trim_start_matches(':')
                .split_whitespace()
                .map(str::to_string)
                .collect();
            let fence = lines.get(i + 1).and_then(|l| l.strip_prefix("```"));
            let lang = fence.map(str::trim).unwrap_or("");
            assert!(
                ["sh", "bash", "console", "yaml"].contains(&lang),
                "{}:{}: a test marker must stand right before a sh, bash, console or yaml block",
                rel(&page),
                i + 1
            );
            let body: String = lines[i + 2..]
                .iter()
                .take_while(|l| !l.starts_with("```"))
                .map(|l| format!("{l}\n"))
                .collect();
            blocks += 1;
            let dir = tempfile::tempdir().unwrap();
            for sub in ["experiments", "examples"] {
                std::os::unix::fs::symlink(repo().join(sub), dir.path().join(sub)).unwrap();
            }
            for mut args in command_lines(lang, &body) {
                if args[0] == "python3" {
                    if !python_ready() {
                        break;
                    }
                    commands += 1;
                    let o = std::process::Command::new("python3")
                        .args(&args[1..])
                        .env("KFMC_BIN", env!("CARGO_BIN_EXE_kfmc"))
                        .current_dir(dir.path())
                        .output()
                        .unwrap();
                    assert!(
                        o.status.success(),
                        "{}:{}: `{}` exited with {:?}:\n{}",
                        rel(&page),
                        i + 1,
                        args.join(" "),
                        o.status.code(),
                        String::from_utf8_lossy(&o.stderr)
                    );
                    continue;
                }
                let runs_a_study = ["run", "check", "simulate", "power", "tune"]
                    .contains(&args.first().map_or("", String::as_str));
                if runs_a_study {
                    // ARGS are `--flag value` pairs; one the command sets itself replaces
                    // the command's value (a documented `--runs 20` runs with ARGS' count).
                    for pair in extra.chunks(2) {
                        match args.iter().position(|a| *a == pair[0]) {
                            Some(i) if pair.len() == 2 && i + 1 < args.len() => {
                                args[i + 1] = pair[1].clone()
                            }
                            _ => args.extend(pair.iter().cloned()),
                        }
                    }
                    args.push("--quiet".into());
                }
                commands += 1;
                let o = crate::common::kfmc()
                    .args(&args)
                    .current_dir(dir.path())
                    .output()
                    .unwrap();
                assert!(
                    o.status.success(),
                    "{}:{}: `kfmc {}` exited with {:?}:\n{}",
                    rel(&page),
                    i + 1,
                    args.join(" "),
                    o.status.code(),
                    String::from_utf8_lossy(&o.stderr)
                );
            }
        }
    }
    assert!(
        blocks >= 3 && commands >= 5,
        "only {blocks} marked blocks with {commands} commands"
    );
}

/// The generated column list of `docs/src/reference/tables.md`.
fn tables_reference() -> String {
    use kfmc::output::schema::{self, ColumnDef, Dtype};
    let q: &[&str] = &["<q>"];
    let tables: Vec<(&str, Vec<ColumnDef>)> = vec![
        ("runs", schema::runs(q)),
        ("steps", schema::steps(q, Some(&["<block>"]))),
        ("run_steps", schema::run_steps()),
        ("summary", schema::summary()),
        ("sensors", schema::sensors()),
        ("consistency", schema::consistency(Some(&["<block>"]))),
        ("sequential", schema::sequential()),
        ("divergence", schema::divergence()),
        ("divergence_runs", schema::divergence_runs()),
        ("traces", schema::traces(q, &["<u>"], &["<z>"], &["<w>"])),
        ("tuning", schema::tuning(q)),
        ("tuned", schema::tuned()),
        ("tune_trace", schema::tune_trace(&["<element>"])),
        (
            "estimates",
            schema::with_variant_columns(kfmc::score::estimate_columns(q, &["<z>"]), [true; 2]),
        ),
        ("truth", schema::truth(q, &["<w>"])),
        ("measurements", schema::measurements(&["<z>"], &["<u>"])),
        ("initial", schema::initial(q)),
        ("power", kfmc::power::columns()),
        ("ulog_samples", schema::ulog_samples()),
        ("ulog_summary", schema::ulog_summary()),
    ];
    let documented: Vec<&str> = tables.iter().map(|(t, _)| *t).collect();
    assert_eq!(
        documented,
        schema::TABLES,
        "a table was added to output::schema::TABLES: add it here"
    );
    let mut out = String::new();
    for (table, cols) in tables {
        out += &format!("\n### `{table}.parquet`\n\n| column | type |\n|---|---|\n");
        for c in cols {
            // One placeholder stands for every quantity, so the covariance's single
            // `P_<q>_<q>` (and `A_…`) stands for the whole triangle (or matrix).
            let name = c
                .name
                .replace("P_<q>_<q>", "P_<qi>_<qj>")
                .replace("A_<q>_<q>", "A_<qi>_<qj>")
                .replace("S_<z>_<z>", "S_<zi>_<zj>");
            let ty = match c.dtype {
                Dtype::Str => "string",
                Dtype::F64 => "float64",
                Dtype::F32 => "float32",
                Dtype::I64 => "int64",
                Dtype::U64 => "uint64",
                Dtype::Bool => "boolean",
            };
            out += &format!("| `{name}` | {ty} |\n");
        }
    }
    out
}

#[test]
fn the_tables_reference_is_generated_from_the_schema() {
    const BEGIN: &str = "<!-- BEGIN GENERATED: tables -->\n";
    const END: &str = "<!-- END GENERATED: tables -->";
    let path = repo().join("docs/src/reference/tables.md");
    let page = std::fs::read_to_string(&path).unwrap();
    let (a, b) = (
        page.find(BEGIN).expect("the BEGIN marker") + BEGIN.len(),
        page.find(END).expect("the END marker"),
    );
    let want = tables_reference();
    if page[a..b] == want {
        return;
    }
    if std::env::var_os("KFMC_BLESS").is_some() {
        std::fs::write(&path, format!("{}{want}{}", &page[..a], &page[b..])).unwrap();
        return;
    }
    let diff: Vec<String> = want
        .lines()
        .zip(page[a..b].lines().chain(std::iter::repeat("")))
        .filter(|(w, h)| w != h)
        .take(10)
        .map(|(w, h)| format!("- {h}\n+ {w}"))
        .collect();
    panic!(
        "docs/src/reference/tables.md differs from kfmc::output::schema (first differences, - page + code):\n{}\nrewrite it with KFMC_BLESS=1 cargo test --release --test it docs::readme_snippets::",
        diff.join("\n")
    );
}

#[test]
fn link_and_heading_parsing() {
    let t = "see [a](x.md#b-c) and ![i](../f.png)\n`[no](code.md)`\n```\n[no](block.md)\n```\n<img src=\"p.svg\">";
    assert_eq!(link_targets(t), ["x.md#b-c", "../f.png", "p.svg"]);
    assert_eq!(
        heading_ids("# A: `[[x.y]]` z\n## A: `[[x.y]]` z\n```\n# not\n```\n### Q × 2"),
        ["a-xy-z", "a-xy-z-1", "q--2"]
    );
    assert_eq!(
        command_lines(
            "console",
            "$ cargo run --release -- run a.toml\nout\n$ kfmc summary d # c\n$ echo"
        ),
        [vec!["run", "a.toml"], vec!["summary", "d"]]
    );
}
