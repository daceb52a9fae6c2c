//! The check's cases as a readable report and as JUnit XML for CI systems.

use std::fmt::Write as _;

use super::CaseResult;

/// Counts of a check's cases: (failed, incomplete); the rest passed.
pub fn tally(cases: &[CaseResult]) -> (usize, usize) {
    let incomplete = cases.iter().filter(|c| c.incomplete).count();
    let failed = cases.iter().filter(|c| !c.pass && !c.incomplete).count();
    (failed, incomplete)
}

/// The readable report of the check `program` (`kfmc` or a plugin crate's binary) ran.
pub fn render(program: &str, experiment: &str, cases: &[CaseResult]) -> String {
    let (failed, incomplete) = tally(cases);
    let mut s = format!(
        "{program} check {experiment}: {} cases, {} passed, {failed} failed, {incomplete} incomplete\n",
        cases.len(),
        cases.len() - failed - incomplete
    );
    let w = cases
        .iter()
        .map(|c| c.name.chars().count())
        .max()
        .unwrap_or(10);
    // The outcome column is as wide as its widest word.
    let o = if incomplete > 0 { 10 } else { 4 };
    for c in cases {
        let _ = writeln!(
            s,
            "  {:<o$}  {:<w$}  {}",
            if c.incomplete {
                "INCOMPLETE"
            } else if c.pass {
                "PASS"
            } else {
                "FAIL"
            },
            c.name,
            c.detail
        );
    }
    s
}

fn xml_escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
        .replace('\'', "&apos;")
}

/// JUnit XML: one `<testcase>` per case, failures with their numbers; an incomplete case is
/// a `<failure type="incomplete">` whose message names the cell and the count.
pub fn junit(program: &str, experiment: &str, cases: &[CaseResult], seconds: f64) -> String {
    let (failed, incomplete) = tally(cases);
    let failures = failed + incomplete;
    let mut s = String::from("<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n");
    let _ = writeln!(
        s,
        "<testsuites name=\"{} check\" tests=\"{}\" failures=\"{failures}\" time=\"{seconds:.3}\">",
        xml_escape(program),
        cases.len()
    );
    let _ = writeln!(
        s,
        "  <testsuite name=\"{}\" tests=\"{}\" failures=\"{failures}\" errors=\"0\" time=\"{seconds:.3}\">",
        xml_escape(experiment),
        cases.len()
    );
    for c in cases {
        let _ = write!(
            s,
            "    <testcase classname=\"{}.{}.{}\" name=\"{}\"",
            xml_escape(program),
            xml_escape(experiment),
            xml_escape(&c.kind),
            xml_escape(&c.name)
        );
        if c.pass {
            let _ = writeln!(
                s,
                ">\n      <system-out>{}</system-out>\n    </testcase>",
                xml_escape(&c.detail)
            );
        } else {
            let kind = if c.incomplete { "incomplete" } else { "failed" };
            let _ = writeln!(
                s,
                ">\n      <failure type=\"{kind}\" message=\"{}\">{}</failure>\n    </testcase>",
                xml_escape(&c.detail),
                xml_escape(&c.detail)
            );
        }
    }
    s.push_str("  </testsuite>\n</testsuites>\n");
    s
}
