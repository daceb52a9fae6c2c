//! Runs in groups ("lanes"): the switch that lets a trial run several runs of one cell at
//! once, and the instruction set the running CPU offers.
//!
//! The executor hands a trial up to `width` consecutive runs of one cell
//! ([`crate::runner::Executor::run_groups`]); a trial that can share work across them (the
//! linear Kalman filters compute P, S and K once per group) does, every other runs them one
//! by one. Results never depend on the width: every run performs the scalar path's
//! operations in the same order, so `off` exists to prove it and to rule it out.

/// The environment variable that sets the mode when no `--lanes` / `lanes=` is given, so it
/// reaches scripts (Python, Slurm) that do not pass the flag.
pub const ENV: &str = "KFMC_LANES";

/// Whether runs are handed to trials in groups.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LanesMode {
    /// Groups as wide as the CPU's vector registers hold f64 lanes ([`Isa::detect`]).
    #[default]
    Auto,
    /// One run at a time: the per-unit scalar path.
    Off,
}

impl LanesMode {
    /// Parses `auto` or `off` (what `--lanes`, `KFMC_LANES` and Python's `lanes=` take).
    pub fn parse(s: &str) -> Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "auto" => Ok(LanesMode::Auto),
            "off" => Ok(LanesMode::Off),
            other => Err(format!("lanes must be \"auto\" or \"off\", not {other:?}")),
        }
    }

    /// The mode `KFMC_LANES` asks for: `None` when it is unset or empty, an error naming the
    /// variable when it holds anything but `auto` or `off`.
    pub fn from_env() -> Result<Option<Self>, String> {
        match std::env::var(ENV) {
            Ok(v) if !v.trim().is_empty() => Self::parse(&v)
                .map(Some)
                .map_err(|e| format!("{ENV}={v:?}: {e}")),
            _ => Ok(None),
        }
    }

    /// The mode a command runs in: its flag when given, else `KFMC_LANES`, else auto.
    pub fn resolve(flag: Option<Self>) -> Result<Self, String> {
        match flag {
            Some(m) => Ok(m),
            None => Ok(Self::from_env()?.unwrap_or_default()),
        }
    }

    /// The mode of a plan built without a command (library use, tuning): `KFMC_LANES` when it
    /// is valid, else auto (a command reports an invalid value through [`Self::resolve`]).
    pub fn env_or_auto() -> Self {
        Self::from_env().ok().flatten().unwrap_or_default()
    }

    /// The instruction set this mode runs with: the detected one, or scalar when off.
    pub fn isa(self) -> Isa {
        match self {
            LanesMode::Auto => Isa::detect(),
            LanesMode::Off => Isa::Scalar,
        }
    }

    /// Runs per group: the f64 lanes of [`Self::isa`] (1 when off).
    pub fn width(self) -> usize {
        self.isa().width()
    }

    /// `"auto"` or `"off"`.
    pub fn name(self) -> &'static str {
        match self {
            LanesMode::Auto => "auto",
            LanesMode::Off => "off",
        }
    }
}

/// The widest vector instruction set the running CPU has, detected at run time (one binary
/// for every CPU; no `-C target-cpu` needed).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Isa {
    /// x86-64 AVX-512F: 8 f64 lanes.
    Avx512,
    /// x86-64 AVX2 with FMA: 4 f64 lanes.
    Avx2,
    /// x86-64 baseline SSE2: 2 f64 lanes.
    Sse2,
    /// aarch64 NEON: 2 f64 lanes.
    Neon,
    /// No vector unit known to kfmc, or lanes turned off: 1 lane.
    Scalar,
}

impl Isa {
    /// The widest set this CPU has.
    pub fn detect() -> Isa {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f") {
                return Isa::Avx512;
            }
            if std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
            {
                return Isa::Avx2;
            }
            Isa::Sse2
        }
        #[cfg(target_arch = "aarch64")]
        {
            if std::arch::is_aarch64_feature_detected!("neon") {
                return Isa::Neon;
            }
            Isa::Scalar
        }
        #[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
        {
            Isa::Scalar
        }
    }

    /// f64 lanes of one vector register.
    pub fn width(self) -> usize {
        match self {
            Isa::Avx512 => 8,
            Isa::Avx2 => 4,
            Isa::Sse2 | Isa::Neon => 2,
            Isa::Scalar => 1,
        }
    }

    /// The name the manifest records: `avx512`, `avx2`, `sse2`, `neon` or `scalar`.
    pub fn name(self) -> &'static str {
        match self {
            Isa::Avx512 => "avx512",
            Isa::Avx2 => "avx2",
            Isa::Sse2 => "sse2",
            Isa::Neon => "neon",
            Isa::Scalar => "scalar",
        }
    }
}

/// The groups of `units` (indices numbered cell-major, `runs` per cell) when up to `width`
/// consecutive runs of one cell form a group: a group starts at every run that is a multiple
/// of `width` and at the first unit of `units`, and never crosses a cell, so the tail of a
/// cell whose run count is not a multiple of `width` is a shorter group. The groups tile
/// `units` in order.
pub fn groups(
    units: std::ops::Range<usize>,
    runs: usize,
    width: usize,
) -> impl Iterator<Item = std::ops::Range<usize>> {
    let (runs, width) = (runs.max(1), width.max(1));
    let end = units.end;
    let mut start = units.start;
    std::iter::from_fn(move || {
        if start >= end {
            return None;
        }
        let run = start % runs;
        let len = (width - run % width).min(runs - run).min(end - start);
        let g = start..start + len;
        start += len;
        Some(g)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn groups_tile_the_units_within_cells_at_multiples_of_the_width() {
        // 10 runs per cell, width 4: runs 0–3, 4–7, 8–9 of each cell.
        let g: Vec<_> = groups(0..20, 10, 4).collect();
        assert_eq!(g, vec![0..4, 4..8, 8..10, 10..14, 14..18, 18..20]);
        // A window that starts inside a group ends that group at the next multiple.
        let g: Vec<_> = groups(6..13, 10, 4).collect();
        assert_eq!(g, vec![6..8, 8..10, 10..13]);
        // Width 1 is one unit per group.
        assert_eq!(groups(3..6, 10, 1).count(), 3);
    }

    #[test]
    fn the_mode_parses_its_two_names_and_off_is_scalar() {
        assert_eq!(LanesMode::parse("off"), Ok(LanesMode::Off));
        assert_eq!(LanesMode::parse(" AUTO "), Ok(LanesMode::Auto));
        assert!(LanesMode::parse("on").is_err());
        assert_eq!(LanesMode::Off.width(), 1);
        assert_eq!(LanesMode::Off.isa(), Isa::Scalar);
        assert_eq!(LanesMode::resolve(Some(LanesMode::Off)), Ok(LanesMode::Off));
    }
}
