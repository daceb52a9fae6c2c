//! Writes the flight logs kfmc simulates (a filter with a known S) into a folder, and times
//! `kfmc ulog nis` on a folder of many of them.
//!
//! ```text
//! cargo run --release --example ulog_flights -- DIR            # the test set
//! cargo run --release --example ulog_flights -- DIR COUNT      # COUNT consistent flights
//! ```
//!
//! The test set is `kfmc::ulog::simulate::Flight::presets()`: consistent, over-confident,
//! over-conservative, correlated, a reset, non-stationary, a primary switch, the innovations
//! topics, and a one-hour flight. With COUNT, the folder gets COUNT consistent 10-minute
//! flights of independent seeds, and the example judges the folder and prints the time.

use kfmc::ulog::simulate::{Flight, write};

fn main() {
    let mut args = std::env::args().skip(1);
    let dir = std::path::PathBuf::from(args.next().expect("usage: ulog_flights DIR [COUNT]"));
    std::fs::create_dir_all(&dir).expect("the folder");
    match args.next().and_then(|c| c.parse::<u64>().ok()) {
        None => {
            for f in Flight::presets() {
                let p = write(&f, &dir).expect("written");
                println!("{}", p.display());
            }
        }
        Some(count) => {
            for i in 0..count {
                let f = Flight::consistent(&format!("flight_{i:03}"), 1000 + i);
                write(&f, &dir).expect("written");
            }
            let out = dir.with_extension("nis");
            let mut opts = kfmc::ulog::NisOptions::new(out.clone());
            opts.force = true;
            let t = std::time::Instant::now();
            let o = kfmc::ulog::nis(&dir, &opts, |_, _| {}).expect("judged");
            let (failed, incomplete) = o.tally();
            println!(
                "{count} logs judged in {:.2} s ({:.1} ms per log); {} cases, {failed} failed, {incomplete} incomplete; tables in {}",
                t.elapsed().as_secs_f64(),
                1e3 * t.elapsed().as_secs_f64() / count as f64,
                o.cases.len(),
                out.display()
            );
        }
    }
}
