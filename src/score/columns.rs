//! The columns of an estimates file: the covariance forms, the columns kfmc writes, and
//! the check of the columns a file has against the study's layout.

use std::path::Path;

use crate::error::OutputError;
use crate::linalg::so3::EulerRotation;
use crate::output::schema::{ColumnDef, Dtype, covariance_columns};

use super::rotation::quaternion_columns;
use super::{FAILED_COLUMN, VARIANT_COLUMNS, format_err};

/// How an estimates file gives the covariance. Each form has n(n + 1)/2 columns. A Cholesky
/// factor however rounded (to float32, say) still gives a positive semi-definite P = L Lᵀ,
/// and its rounding moves the NEES by about √κ times the rounding where P's entries move it
/// by about κ times (κ the condition number of P's correlation matrix); the correlations are
/// the form people read, σ and ρ.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CovarianceForm {
    /// `P_<qi>_<qj>`, the lower triangle.
    Lower,
    /// `L_<i>_<j>`, a lower Cholesky factor: P = L Lᵀ.
    Cholesky,
    /// `var_<q>`, the diagonal, and `corr_<qi>_<qj>`, the correlations below it:
    /// P_ij = corr_ij √(var_i var_j).
    Correlation,
}

impl CovarianceForm {
    /// The column of entry (i, j), i ≥ j, of the covariance's lower triangle in this form.
    pub(super) fn column(self, q: &[&str], i: usize, j: usize) -> String {
        match self {
            CovarianceForm::Lower => format!("P_{}_{}", q[i], q[j]),
            CovarianceForm::Cholesky => format!("L_{i}_{j}"),
            CovarianceForm::Correlation if i == j => format!("var_{}", q[i]),
            CovarianceForm::Correlation => format!("corr_{}_{}", q[i], q[j]),
        }
    }

    /// This form's columns for these quantities, in the order of the lower triangle
    /// (row by row): what a file gives in place of the `P_` columns.
    pub fn columns(self, quantities: &[&str]) -> Vec<String> {
        (0..quantities.len())
            .flat_map(|i| (0..=i).map(move |j| (i, j)))
            .map(|(i, j)| self.column(quantities, i, j))
            .collect()
    }

    /// Whether a column name belongs to this form (by its prefix).
    fn owns(self, name: &str) -> bool {
        match self {
            CovarianceForm::Lower => name.starts_with("P_"),
            CovarianceForm::Cholesky => name.starts_with("L_"),
            CovarianceForm::Correlation => name.starts_with("var_") || name.starts_with("corr_"),
        }
    }

    /// Every form.
    pub const ALL: [CovarianceForm; 3] = [
        CovarianceForm::Lower,
        CovarianceForm::Cholesky,
        CovarianceForm::Correlation,
    ];
}

/// The covariance forms and the float32 columns a file may use instead of what
/// [`estimate_columns`] lists, for a study with these quantities: the lines `kfmc schema
/// estimates` prints.
pub fn covariance_forms_text(quantities: &[&str]) -> String {
    let n = quantities.len();
    let list = |form: CovarianceForm| {
        let all = form.columns(quantities);
        if all.len() > 4 {
            format!("{}, {}, …, {}", all[0], all[1], all[all.len() - 1])
        } else {
            all.join(", ")
        }
    };
    format!(
        "\ncovariance, one form per file (n(n+1)/2 = {} columns each):\n  P_<qi>_<qj>: the lower triangle, as listed above\n  L_<i>_<j> (0-based, i >= j): a lower Cholesky factor, P = L L^T: {}\n  var_<q> and corr_<qi>_<qj> (qi after qj): the diagonal and the correlations, P_ij = corr_ij sqrt(var_i var_j): {}\nvalue columns may be float32, read as float64 exactly (keys stay as listed); keep est_ and quat_ float64, since the error truth - estimate needs the estimate's every digit; a float32 L_ still gives a positive semi-definite P = L L^T\n",
        n * (n + 1) / 2,
        list(CovarianceForm::Cholesky),
        list(CovarianceForm::Correlation),
    )
}

/// The columns an estimates file has, beyond the keys.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct EstimateColumns {
    /// Evaluated quantities.
    pub quantities: Vec<String>,
    /// Measurement components.
    pub measurements: Vec<String>,
    /// The covariance form.
    pub covariance: CovarianceForm,
    /// Whether `nu_*` and `S_*` are present.
    pub innovations: bool,
    /// Whether `A_*` is present.
    pub transition: bool,
    /// The rotations given as quaternions (their `est_` columns are formed from them on
    /// reading, and their covariance is already the rotation error's).
    pub quaternions: Vec<EulerRotation>,
}

impl EstimateColumns {
    pub(super) fn nq(&self) -> usize {
        self.quantities.len()
    }
    pub(super) fn nz(&self) -> usize {
        self.measurements.len()
    }
    pub(super) fn ntri(&self) -> usize {
        self.nq() * (self.nq() + 1) / 2
    }
    fn ztri(&self) -> usize {
        self.nz() * (self.nz() + 1) / 2
    }
    /// f64 values per row in the spill file.
    pub(super) fn width(&self) -> usize {
        self.nq()
            + self.ntri()
            + if self.innovations {
                self.nz() + self.ztri()
            } else {
                0
            }
            + if self.transition {
                self.nq() * self.nq()
            } else {
                0
            }
    }

    /// The columns a file has: [`EstimateColumns::value_columns`] with each quaternion
    /// rotation's three `est_` columns replaced by its four `quat_` ones.
    pub fn file_columns(&self) -> Vec<String> {
        let mut c = self.value_columns();
        for r in self.quaternions.iter().rev() {
            c.splice(
                r.first..r.first + 3,
                quaternion_columns(&self.quantities, r),
            );
        }
        c
    }

    /// The value columns in spill order.
    pub fn value_columns(&self) -> Vec<String> {
        let q: Vec<&str> = self.quantities.iter().map(String::as_str).collect();
        let z: Vec<&str> = self.measurements.iter().map(String::as_str).collect();
        let mut c: Vec<String> = q.iter().map(|n| format!("est_{n}")).collect();
        match self.covariance {
            CovarianceForm::Lower => c.extend(covariance_columns(&q).into_iter().map(|d| d.name)),
            form => {
                for i in 0..q.len() {
                    for j in 0..=i {
                        c.push(form.column(&q, i, j));
                    }
                }
            }
        }
        if self.innovations {
            c.extend(z.iter().map(|n| format!("nu_{n}")));
            for (i, zi) in z.iter().enumerate() {
                for zj in &z[..=i] {
                    c.push(format!("S_{zi}_{zj}"));
                }
            }
        }
        if self.transition {
            for qi in &q {
                for qj in &q {
                    c.push(format!("A_{qi}_{qj}"));
                }
            }
        }
        c
    }
}

/// Every column of an estimates file for a study with these quantities and measurements, in
/// the order `kfmc run --export-estimates` writes them (`kfmc schema estimates`).
pub fn estimate_columns(quantities: &[&str], measurements: &[&str]) -> Vec<ColumnDef> {
    estimate_columns_with(quantities, measurements, &[])
}

/// The precision of the value columns kfmc exports (`kfmc run --export-estimates-precision`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum EstimatePrecision {
    /// Every value column float64 (the default).
    #[default]
    F64,
    /// The covariance, innovation, S and A columns float32, rounded to nearest; the
    /// estimates (`est_`, `quat_`) stay float64, since the error truth − estimate needs
    /// every digit of the estimate. About half the bytes; read back as f64, exactly.
    F32,
}

/// [`estimate_columns`] for a study whose layout has `rotations`: kfmc writes each as a
/// quaternion with the rotation error's covariance.
pub fn estimate_columns_with(
    quantities: &[&str],
    measurements: &[&str],
    rotations: &[EulerRotation],
) -> Vec<ColumnDef> {
    estimate_columns_in(quantities, measurements, rotations, EstimatePrecision::F64)
}

/// [`estimate_columns_with`] in a precision: with [`EstimatePrecision::F32`] every value
/// column but the estimates is float32.
pub fn estimate_columns_in(
    quantities: &[&str],
    measurements: &[&str],
    rotations: &[EulerRotation],
    precision: EstimatePrecision,
) -> Vec<ColumnDef> {
    let cols = EstimateColumns {
        quantities: quantities.iter().map(|s| s.to_string()).collect(),
        measurements: measurements.iter().map(|s| s.to_string()).collect(),
        covariance: CovarianceForm::Lower,
        innovations: true,
        transition: true,
        quaternions: rotations.to_vec(),
    };
    let mut c = key_columns();
    c.push(ColumnDef {
        name: FAILED_COLUMN.into(),
        dtype: Dtype::Bool,
    });
    c.extend(cols.file_columns().into_iter().map(|name| {
        let estimate = name.starts_with("est_") || name.starts_with("quat_");
        let dtype = match precision {
            EstimatePrecision::F32 if !estimate => Dtype::F32,
            _ => Dtype::F64,
        };
        ColumnDef { name, dtype }
    }));
    c
}

/// The key columns of an estimates file.
pub fn key_columns() -> Vec<ColumnDef> {
    [
        ("scenario", Dtype::Str),
        ("noise_scale", Dtype::F64),
        ("run", Dtype::I64),
        ("step", Dtype::I64),
        ("filter", Dtype::Str),
    ]
    .into_iter()
    .map(|(n, dtype)| ColumnDef {
        name: n.into(),
        dtype,
    })
    .collect()
}

/// Which value columns a file has, checked against the study's layout: every column must be
/// a key or a known value column, and each group complete.
pub(super) fn detect_columns(
    path: &Path,
    names: &[String],
    quantities: &[&str],
    measurements: &[&str],
    rotations: &[EulerRotation],
) -> Result<EstimateColumns, OutputError> {
    let has = |n: &str| names.iter().any(|c| c == n);
    let owned: Vec<String> = quantities.iter().map(|s| s.to_string()).collect();
    let mut quaternions = Vec::new();
    for r in rotations {
        let quat = quaternion_columns(&owned, r);
        if quat.iter().any(|c| has(c)) {
            if let Some(e) = owned[r.first..r.first + 3]
                .iter()
                .map(|q| format!("est_{q}"))
                .find(|e| has(e))
            {
                return Err(format_err(
                    path,
                    format!(
                        "both `{e}` and `{}`: give the rotation one way, as Euler angles est_* (with their covariance) or as a quaternion quat_* (with the rotation error's covariance)",
                        quat[0]
                    ),
                ));
            }
            quaternions.push(*r);
        }
    }
    let base = |covariance, innovations, transition| EstimateColumns {
        quantities: owned.clone(),
        measurements: measurements.iter().map(|s| s.to_string()).collect(),
        covariance,
        innovations,
        transition,
        quaternions: quaternions.clone(),
    };
    // The first column of each covariance form the file has: one form only.
    let forms: Vec<(CovarianceForm, &String)> = CovarianceForm::ALL
        .into_iter()
        .filter_map(|f| names.iter().find(|c| f.owns(c)).map(|c| (f, c)))
        .collect();
    if let [(_, a), (_, b), ..] = forms[..] {
        return Err(format_err(
            path,
            format!(
                "both `{a}` and `{b}`: give the covariance one way, as the lower triangle P_<qi>_<qj>, a lower Cholesky factor L_<i>_<j>, or the variances var_<q> with the correlations corr_<qi>_<qj>"
            ),
        ));
    }
    let covariance = forms.first().map_or(CovarianceForm::Lower, |(f, _)| *f);
    let innovations = names
        .iter()
        .any(|c| c.starts_with("nu_") || c.starts_with("S_"));
    let transition = names.iter().any(|c| c.starts_with("A_"));
    let cols = base(covariance, innovations, transition);
    let expected = cols.file_columns();
    for k in key_columns() {
        if !has(&k.name) {
            return Err(format_err(path, format!("missing key column `{}`", k.name)));
        }
    }
    for e in &expected {
        if !has(e) {
            return Err(format_err(
                path,
                format!(
                    "missing column `{e}` (the file has {} value columns, this study's format {}; `kfmc schema estimates SPEC` lists them)",
                    names
                        .iter()
                        .filter(|n| !key_columns().iter().any(|k| k.name == **n)
                            && !VARIANT_COLUMNS.contains(&n.as_str())
                            && n.as_str() != FAILED_COLUMN)
                        .count(),
                    expected.len()
                ),
            ));
        }
    }
    let mut keys: Vec<String> = key_columns().into_iter().map(|c| c.name).collect();
    keys.extend(VARIANT_COLUMNS.map(String::from));
    keys.push(FAILED_COLUMN.into());
    if let Some(extra) = names
        .iter()
        .find(|n| !keys.contains(n) && !expected.contains(n))
    {
        return Err(format_err(
            path,
            format!(
                "unexpected column `{extra}` (not a key nor a value column of this study; `kfmc schema estimates SPEC` lists them)"
            ),
        ));
    }
    Ok(cols)
}
