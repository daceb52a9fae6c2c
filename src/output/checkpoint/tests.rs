//! Unit tests of `src/output/checkpoint.rs`, kept apart so that the module reads as its role.

use super::*;

fn cols() -> Vec<ColumnDef> {
    [
        ("s", Dtype::Str),
        ("x", Dtype::F64),
        ("i", Dtype::I64),
        ("u", Dtype::U64),
        ("b", Dtype::Bool),
    ]
    .into_iter()
    .map(|(n, d)| ColumnDef {
        name: n.into(),
        dtype: d,
    })
    .collect()
}

fn rows() -> Vec<Vec<Value<'static>>> {
    vec![
        vec![
            Value::Str("basic"),
            Value::F64(Some(-0.0)),
            Value::I64(Some(-7)),
            Value::U64(u64::MAX),
            Value::Bool(Some(true)),
        ],
        vec![
            Value::Str(""),
            Value::F64(None),
            Value::I64(None),
            Value::U64(0),
            Value::Bool(None),
        ],
        vec![
            Value::Str("ωθ"),
            Value::F64(Some(f64::INFINITY)),
            Value::I64(Some(i64::MIN)),
            Value::U64(3),
            Value::Bool(Some(false)),
        ],
    ]
}

/// Values and nulls come back bit for bit (−0.0, ∞, extremes, UTF-8, empty strings), and
/// a NaN comes back as the null the table stores for it.
#[test]
fn rows_replay_exactly_and_a_reopened_journal_drops_the_unsynced_tail() {
    let d = tempfile::tempdir().unwrap();
    let path = d.path().join("t.journal");
    let mut j = Journal::create(&path, &study()).unwrap();
    for r in rows() {
        j.record(&r).unwrap();
    }
    let (bytes, rows_done) = j.end_cell(1).unwrap();
    assert_eq!(j.sync().unwrap(), (bytes, rows_done));
    assert_eq!(rows_done, 3);
    j.record(&[
        Value::Str("lost"),
        Value::F64(Some(f64::NAN)),
        Value::I64(None),
        Value::U64(1),
        Value::Bool(None),
    ])
    .unwrap();
    j.sync().unwrap();
    drop(j);

    let mut back: Vec<String> = Vec::new();
    let n = replay(&path, bytes, 1, &cols(), &study(), |r| {
        back.push(format!("{r:?}"));
        Ok(())
    })
    .unwrap();
    assert_eq!(n, 3);
    let want: Vec<String> = rows().iter().map(|r| format!("{r:?}")).collect();
    assert_eq!(back, want);
    let mut neg_zero = None;
    replay(&path, bytes, 1, &cols(), &study(), |r| {
        if let Value::F64(Some(x)) = r[1] {
            neg_zero.get_or_insert(x.to_bits());
        }
        Ok(())
    })
    .unwrap();
    assert_eq!(neg_zero, Some((-0.0f64).to_bits()));

    let mut j = Journal::reopen(&path, bytes, 3).unwrap();
    assert_eq!(std::fs::metadata(&path).unwrap().len(), bytes);
    j.record(&rows()[1]).unwrap();
    let (b2, r2) = j.end_cell(2).unwrap();
    j.sync().unwrap();
    assert_eq!(r2, 4);
    let mut last = String::new();
    assert_eq!(
        replay(&path, b2, 2, &cols(), &study(), |r| {
            last = format!("{r:?}");
            Ok(())
        })
        .unwrap(),
        4
    );
    assert_eq!(last, format!("{:?}", rows()[1]));
}

#[test]
fn a_journal_shorter_than_its_checkpoint_is_refused_as_damaged() {
    let d = tempfile::tempdir().unwrap();
    let path = d.path().join("t.journal");
    let mut j = Journal::create(&path, &study()).unwrap();
    j.record(&rows()[0]).unwrap();
    let (bytes, _) = j.end_cell(1).unwrap();
    j.sync().unwrap();
    drop(j);
    let err = Journal::reopen(&path, bytes + 5, 2)
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("damaged checkpoint journal"), "{err}");
    // Bytes lost inside the frame the checkpoint vouches for.
    std::fs::OpenOptions::new()
        .write(true)
        .open(&path)
        .unwrap()
        .set_len(bytes - 3)
        .unwrap();
    let err = replay(&path, bytes, 1, &cols(), &study(), |_| Ok(()))
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("damaged checkpoint journal"), "{err}");
}

/// The identity of the test journals' study.
fn study() -> Index {
    Index {
        kfmc_version: "x".into(),
        spec_hash: "h".into(),
        master_seed: 7,
        world_stamp: "w7".into(),
        runs_per_cell: 2,
        cells: 6,
        first_cell: 0,
        end_cell: 6,
        trace_runs: 0,
        export_estimates: false,
        export_f32: false,
        journal_format: JOURNAL_FORMAT,
        cells_done: 0,
        tables: Vec::new(),
    }
}

/// A journal names the study that wrote it: replayed for a study of another seed (an
/// index whose `master_seed` was edited, resumed with that seed), another world or spec,
/// it is refused naming the difference; its own study's progress does not matter.
#[test]
fn a_journal_of_another_study_is_refused_whatever_its_index_says() {
    let (_d, path, ends) = journal_of(2);
    let (bytes, _) = ends[1];
    let mut own = study();
    own.cells_done = 2;
    assert_eq!(
        replay(&path, bytes, 2, &cols(), &own, |_| Ok(())).unwrap(),
        6
    );
    let mut seed = study();
    seed.master_seed = 8;
    let mut world = study();
    world.world_stamp = "w8".into();
    let mut spec = study();
    spec.spec_hash = "other".into();
    for (other, why) in [
        (seed, "the master seed changed (7 → 8)"),
        (world, "the simulated world changed (stamp w7 → w8)"),
        (spec, "the spec changed"),
    ] {
        let e = replay(&path, bytes, 2, &cols(), &other, |_| {
            panic!("no row of another study is replayed")
        })
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("holds another study's cells") && e.contains(why) && e.contains("--restart"),
            "{e}"
        );
    }
    // A journal that does not begin with its study (format 2's) is refused too.
    let original = std::fs::read(&path).unwrap();
    let header = ends[0].0 as usize;
    let (_d2, bare, _) = journal_of(0);
    let header_len = std::fs::metadata(&bare).unwrap().len() as usize;
    assert!(header_len > 0 && header_len < header);
    std::fs::write(&path, &original[header_len..]).unwrap();
    let e = replay(
        &path,
        bytes - header_len as u64,
        2,
        &cols(),
        &study(),
        |_| Ok(()),
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("does not begin with the identity of its study"),
        "{e}"
    );
}

/// A journal of `cells` cells of the test rows; returns its path's folder, the path, and
/// the (bytes, rows) at each cell's end.
fn journal_of(cells: u64) -> (tempfile::TempDir, PathBuf, Vec<(u64, u64)>) {
    let d = tempfile::tempdir().unwrap();
    let path = d.path().join("t.journal");
    let mut j = Journal::create(&path, &study()).unwrap();
    let mut ends = Vec::new();
    for c in 1..=cells {
        for r in rows() {
            j.record(&r).unwrap();
        }
        ends.push(j.end_cell(c).unwrap());
    }
    j.sync().unwrap();
    (d, path, ends)
}

fn replayed(path: &Path, bytes: u64, cells: u64) -> Result<Vec<String>, String> {
    let mut back = Vec::new();
    replay(path, bytes, cells, &cols(), &study(), |r| {
        back.push(format!("{r:?}"));
        Ok(())
    })
    .map_err(|e| e.to_string())?;
    Ok(back)
}

/// Every single-bit flip anywhere in the journal is either refused as damaged (with the
/// advice to restart) or, where zstd ignores the bit, replays the very same rows: a
/// journal never replays rows that differ from the ones recorded.
#[test]
fn every_flipped_bit_is_refused_or_harmless() {
    let (_d, path, ends) = journal_of(2);
    let (bytes, _) = ends[1];
    let good = replayed(&path, bytes, 2).unwrap();
    assert_eq!(good.len(), 6);
    let original = std::fs::read(&path).unwrap();
    let (mut refused, mut harmless) = (0, 0);
    for bit in 0..original.len() * 8 {
        let mut flipped = original.clone();
        flipped[bit / 8] ^= 1 << (bit % 8);
        std::fs::write(&path, &flipped).unwrap();
        match replayed(&path, bytes, 2) {
            Err(e) => {
                assert!(
                    e.contains("damaged checkpoint journal") && e.contains("--restart"),
                    "{e}"
                );
                refused += 1;
            }
            Ok(back) => {
                assert_eq!(back, good, "bit {bit} changed the replayed rows");
                harmless += 1;
            }
        }
    }
    assert!(refused > harmless, "{refused} refused, {harmless} harmless");
}

/// The index must describe the journal: a cell count that differs from the cell ends
/// within its bytes, or bytes that stop inside a cell, are refused.
#[test]
fn an_index_that_does_not_describe_its_journal_is_refused() {
    let (_d, path, ends) = journal_of(3);
    for (k, &(bytes, _)) in ends.iter().enumerate() {
        let k = k as u64 + 1;
        assert_eq!(replayed(&path, bytes, k).unwrap().len() as u64, 3 * k);
        for wrong in [0, k - 1, k + 1, 7] {
            if wrong == k {
                continue;
            }
            let e = replayed(&path, bytes, wrong).unwrap_err();
            assert!(
                e.contains(&format!("holds {k} complete cells")) && e.contains("--restart"),
                "{e}"
            );
        }
    }
    // Cut after the second cell's first frame bytes but before its end: not a boundary.
    let e = replayed(&path, ends[1].0 - 1, 2).unwrap_err();
    assert!(e.contains("damaged checkpoint journal"), "{e}");
}

/// An index counting more cells than its range, or a range outside the plan, is refused
/// before any journal is read.
#[test]
fn an_incoherent_index_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let mut i = Index {
        kfmc_version: "x".into(),
        spec_hash: "h".into(),
        master_seed: 1,
        world_stamp: "w".into(),
        runs_per_cell: 2,
        cells: 6,
        first_cell: 2,
        end_cell: 4,
        trace_runs: 0,
        export_estimates: false,
        export_f32: false,
        journal_format: JOURNAL_FORMAT,
        cells_done: 2,
        tables: Vec::new(),
    };
    i.check(d.path()).unwrap();
    i.cells_done = 3;
    let e = i.check(d.path()).unwrap_err().to_string();
    assert!(
        e.contains("counts 3 complete cells of 2") && e.contains("--restart"),
        "{e}"
    );
    i.cells_done = u64::MAX;
    assert!(i.check(d.path()).is_err());
    i.cells_done = 1;
    i.end_cell = 9;
    assert!(i.check(d.path()).is_err());
}
