//! Unit tests of `src/sequential.rs`, kept apart so that the module reads as its role.

use super::*;

/// rpact's own unit tests (tests/testthat/test-f_design_group_sequential.R of the rpact
/// package, which asserts them to 1e-7): an independent implementation of the same
/// definitions. Ours must agree to 1e-5.
fn close(got: &[f64], want: &[f64], tol: f64) {
    assert_eq!(got.len(), want.len());
    for (g, w) in got.iter().zip(want) {
        assert!((g - w).abs() < tol, "got {got:?}, want {want:?}");
    }
}

#[test]
fn obrien_fleming_spending_matches_rpact() {
    // getDesignGroupSequential(kMax = 4, alpha = 0.13, typeOfDesign = "asOF",
    //   informationRates = c(0.4, 0.75, 0.85, 1))
    let d = efficacy(
        &[0.4, 0.75, 0.85, 1.0],
        0.13,
        &Spending::OBrienFleming,
        Sides::One,
    )
    .unwrap();
    close(
        &d.alpha_spent,
        &[0.016665509, 0.080406163, 0.10053322, 0.13],
        1e-8,
    );
    close(
        &d.efficacy,
        &[2.1280732, 1.4368565, 1.422873, 1.2970881],
        1e-5,
    );
    // The classic three equally spaced looks at one-sided 0.025 (gsDesign's sfLDOF
    // example and rpact agree): 3.7103, 2.5114, 1.9930.
    let d = efficacy(
        &[1.0 / 3.0, 2.0 / 3.0, 1.0],
        0.025,
        &Spending::OBrienFleming,
        Sides::One,
    )
    .unwrap();
    close(&d.efficacy, &[3.7103, 2.5114, 1.9930], 1e-4);
}

#[test]
fn pocock_spending_matches_rpact_including_a_study_stopped_early() {
    // getDesignGroupSequential(kMax = 3, alpha = 0.13, typeOfDesign = "asP",
    //   informationRates = c(0.35, 0.7, 1)) (its critical values ignore the non-binding
    //   futility bounds)
    let d = efficacy(&[0.35, 0.7, 1.0], 0.13, &Spending::Pocock, Sides::One).unwrap();
    close(&d.alpha_spent, &[0.061214062, 0.10266465, 0.13], 1e-8);
    close(&d.efficacy, &[1.5446617, 1.4828682, 1.4620058], 1e-5);
    // getDesignGroupSequential(informationRates = c(0.4, 0.7), typeOfDesign = "asP"): the
    // last look before the planned end spends only f(0.7).
    let d = efficacy(&[0.4, 0.7], 0.025, &Spending::Pocock, Sides::One).unwrap();
    close(&d.alpha_spent, &[0.013078429, 0.0197432], 1e-8);
    close(&d.efficacy, &[2.223875, 2.3050796], 1e-5);
}

#[test]
fn power_family_and_user_spending_match_rpact() {
    // asHSD with gamma = 0 is uniform spending, the power family with ρ = 1:
    // getDesignInverseNormal(kMax = 3, informationRates = c(0.2, 0.4, 1), alpha = 0.03,
    //   typeOfDesign = "asHSD", gammaA = 0)
    let d = efficacy(&[0.2, 0.4, 1.0], 0.03, &Spending::Power(1.0), Sides::One).unwrap();
    close(&d.efficacy, &[2.5121443, 2.4228747, 2.0280392], 1e-5);
    // getDesignGroupSequential(typeOfDesign = "asUser",
    //   userAlphaSpending = c(0.01, 0.02, 0.03, 0.05)), α = 0.05, four equal looks.
    let user = Spending::User(vec![0.2, 0.4, 0.6, 1.0]);
    let d = efficacy(&[0.25, 0.5, 0.75, 1.0], 0.05, &user, Sides::One).unwrap();
    close(
        &d.efficacy,
        &[2.3263479, 2.2192994, 2.1201347, 1.8189562],
        1e-5,
    );
}

#[test]
fn two_sided_boundaries_match_rpact_for_the_same_spending() {
    // getDesignGroupSequential(kMax = 4, alpha = 0.025, sided = 2,
    //   informationRates = c(0.3, 0.6, 0.8, 1), typeOfDesign = "WToptimum", ...) spends
    // 0.00054745752, 0.0059439465, 0.014151805, 0.025 (both sides) with these |Z| bounds;
    // given the same spending, ours must find the same bounds.
    let spent = [0.00054745752, 0.0059439465, 0.014151805, 0.02499999];
    let user = Spending::User(spent.iter().map(|s| s / 0.025).collect());
    let d = efficacy(&[0.3, 0.6, 0.8, 1.0], 0.025, &user, Sides::Two).unwrap();
    close(
        &d.efficacy,
        &[3.4563925, 2.7688119, 2.5253005, 2.3512665],
        1e-5,
    );
    // x8b: sided = 2, informationRates = c(0.3, 0.8, 1).
    let spent = [0.0013603353, 0.013978861, 0.02499999];
    let user = Spending::User(spent.iter().map(|s| s / 0.025).collect());
    let d = efficacy(&[0.3, 0.8, 1.0], 0.025, &user, Sides::Two).unwrap();
    close(&d.efficacy, &[3.2029374, 2.4819703, 2.3420706], 1e-5);
}

#[test]
fn non_binding_futility_matches_rpact() {
    // getDesignGroupSequential(kMax = 3, alpha = 0.13, beta = 0.41, typeOfDesign = "asOF",
    //   typeBetaSpending = "bsKD", informationRates = c(0.4, 0.75, 1), gammaB = 2.5,
    //   bindingFutility = FALSE)
    let d = with_futility(
        &[0.4, 0.75, 1.0],
        0.13,
        &Spending::OBrienFleming,
        Sides::One,
        0.41,
        &Spending::Power(2.5),
    )
    .unwrap();
    close(&d.efficacy, &[2.1280732, 1.4368565, 1.2468994], 1e-5);
    let b = d.futility.as_ref().unwrap();
    close(&b[..2], &[-0.83725762, 0.35992547], 1e-5);
    // Its power look by look, cumulative: 0.10903632, 0.42541278, 0.59.
    let p = d.rejection_probabilities(d.drift.unwrap(), Sides::One);
    let cum: Vec<f64> = p
        .iter()
        .scan(0.0, |s, x| {
            *s += x;
            Some(*s)
        })
        .collect();
    close(&cum, &[0.10903632, 0.42541278, 0.59], 1e-5);
}

#[test]
fn the_design_spends_exactly_alpha_under_the_null() {
    // A second route to the level: the rejection probabilities under θ = 0 sum to α, and
    // look by look equal the spending increments (two-sided, ten uneven looks).
    let t: Vec<f64> = [1, 2, 3, 5, 8, 13, 21, 34, 55, 89]
        .iter()
        .map(|&k| k as f64 / 89.0)
        .collect();
    for spending in [Spending::OBrienFleming, Spending::Pocock] {
        let d = efficacy(&t, 0.05, &spending, Sides::Two).unwrap();
        let p = d.rejection_probabilities(0.0, Sides::Two);
        let mut before = 0.0;
        for (pk, cum) in p.iter().zip(&d.alpha_spent) {
            assert!(
                (pk - (cum - before)).abs() < 1e-9,
                "{pk} vs {}",
                cum - before
            );
            before = *cum;
        }
        assert!((p.iter().sum::<f64>() - 0.05).abs() < 1e-9);
    }
}

#[test]
fn one_look_is_the_fixed_sample_test() {
    let d = efficacy(&[1.0], 0.05, &Spending::OBrienFleming, Sides::Two).unwrap();
    // z_{0.975} = 1.959963984540054
    assert!((d.efficacy[0] - 1.959963984540054).abs() < 1e-9);
    let d = efficacy(&[1.0], 0.05, &Spending::Pocock, Sides::One).unwrap();
    assert!((d.efficacy[0] - 1.6448536269514722).abs() < 1e-9);
}

#[test]
fn decisions_follow_the_boundaries() {
    let d = with_futility(
        &[0.4, 0.75, 1.0],
        0.13,
        &Spending::OBrienFleming,
        Sides::One,
        0.41,
        &Spending::Power(2.5),
    )
    .unwrap();
    assert_eq!(d.decide(0, 2.2, Sides::One), Decision::Reject);
    assert_eq!(d.decide(0, -1.0, Sides::One), Decision::Accept);
    assert_eq!(d.decide(0, 0.0, Sides::One), Decision::Continue);
    assert_eq!(d.decide(2, 1.2, Sides::One), Decision::Accept);
    assert_eq!(d.decide(2, 1.25, Sides::One), Decision::Reject);
}

#[test]
fn bad_designs_are_refused() {
    assert!(matches!(
        efficacy(&[0.5, 0.5], 0.05, &Spending::Pocock, Sides::One),
        Err(SequentialError::Fractions(_))
    ));
    assert!(matches!(
        efficacy(&[0.0, 1.0], 0.05, &Spending::Pocock, Sides::One),
        Err(SequentialError::Fractions(_))
    ));
    assert!(matches!(
        efficacy(&[1.0], 1.5, &Spending::Pocock, Sides::One),
        Err(SequentialError::Level { .. })
    ));
    assert!(matches!(
        efficacy(
            &[0.5, 1.0],
            0.05,
            &Spending::User(vec![0.6, 0.5]),
            Sides::One
        ),
        Err(SequentialError::Spending(_))
    ));
}

/// Beyond `MAX_LOOKS` a gate is refused before its looks are expanded: a count of 10¹²
/// looks would otherwise be a vector of 10¹² run counts.
#[test]
fn more_looks_than_the_limit_are_refused_before_they_are_expanded() {
    let gate =
        |looks: Looks| Gate::for_study(1_010_000_000, 0.05, &looks, &Spending::OBrienFleming, None);
    let started = std::time::Instant::now();
    for (looks, n) in [
        (Looks::Count(1_000_000_000_000), 1_000_000_000_000usize),
        (Looks::Count(MAX_LOOKS + 1), MAX_LOOKS + 1),
        (
            // Increasing and ending at the study's runs: too many, nothing else wrong.
            Looks::RunCounts((1..=MAX_LOOKS + 1).map(|k| k * 10_000_000).collect()),
            MAX_LOOKS + 1,
        ),
    ] {
        assert_eq!(
            gate(looks),
            Err(GateError::Looks(format!(
                "{n} looks are more than a gate may take (at most {MAX_LOOKS})"
            )))
        );
    }
    assert!(started.elapsed() < std::time::Duration::from_secs(1));
    assert_eq!(
        gate(Looks::Count(MAX_LOOKS)).unwrap().looks.len(),
        MAX_LOOKS
    );
}

#[test]
fn default_looks_are_even_and_end_at_the_runs() {
    assert_eq!(
        default_looks(100, 10),
        vec![10, 20, 30, 40, 50, 60, 70, 80, 90, 100]
    );
    assert_eq!(
        default_looks(15, 10),
        vec![2, 3, 5, 6, 8, 9, 11, 12, 14, 15]
    );
    assert_eq!(default_looks(3, 10), vec![2, 3]);
}

#[test]
fn the_gate_reads_the_bonferroni_p_value_against_each_tests_nominal_level() {
    let gate = Gate::new(default_looks(100, 4), 0.05, &Spending::OBrienFleming, None).unwrap();
    // One look at N: the fixed verdict (reject when p ≤ α).
    let one = Gate::new(vec![100], 0.05, &Spending::OBrienFleming, None).unwrap();
    assert!((one.nominal_level(0) - 0.025).abs() < 1e-9);
    assert_eq!(one.decide(0, 0.0499), Decision::Reject);
    assert_eq!(one.decide(0, 0.0501), Decision::Accept);
    // Early looks demand far more: the first O'Brien–Fleming look of four at α/2.
    let nu0 = gate.nominal_level(0);
    assert!(nu0 < 1e-4, "{nu0}");
    assert_eq!(gate.decide(0, 2.0 * nu0 * 0.99), Decision::Reject);
    assert_eq!(gate.decide(0, 2.0 * nu0 * 1.01), Decision::Continue);
    assert_eq!(gate.decide(0, 1.0), Decision::Continue);
    // The last look's level is a little below α/2 (what the early looks spent).
    let nu_last = gate.nominal_level(3);
    assert!(nu_last < 0.025 && nu_last > 0.02, "{nu_last}");
}

#[test]
fn a_gate_with_futility_stops_consistent_filters_early() {
    let gate = Gate::new(
        default_looks(100, 10),
        0.05,
        &Spending::OBrienFleming,
        Some((0.1, &Spending::Power(2.0))),
    )
    .unwrap();
    let b = gate.design.futility.as_ref().unwrap();
    // The futility bounds rise to meet the efficacy bound at the last look.
    assert!(b.windows(2).all(|w| w[0] <= w[1]), "{b:?}");
    assert!((b[9] - gate.design.efficacy[9]).abs() < 1e-12);
    // A verdict p of 1 (both tests' p ≥ 0.5) stops a look whose futility bound is above
    // 0.674 (|Z| < b then holds for both tests).
    let k = b.iter().position(|&x| x > 0.6745).unwrap();
    assert_eq!(gate.decide(k, 1.0), Decision::Accept);
    assert_eq!(gate.decide(0, 1.0), Decision::Continue);
}

#[test]
fn linear_beta_spending_raises_the_early_futility_bounds_and_keeps_the_efficacy_bounds() {
    let looks = Looks::Count(10);
    let of = |rho| {
        Gate::for_study_with(
            100,
            0.05,
            &looks,
            &Spending::OBrienFleming,
            Some((0.1, rho)),
        )
        .unwrap()
    };
    let (quadratic, linear) = (of(QUADRATIC_FUTILITY), of(1.0));
    // The default is the quadratic gate of `kfmc power --sequential --futility`.
    let plain = Gate::for_study(100, 0.05, &looks, &Spending::OBrienFleming, Some(0.1));
    assert_eq!(plain.unwrap(), quadratic);
    // Non-binding: the efficacy bounds ignore futility, whatever its spending.
    assert_eq!(linear.design.efficacy, quadratic.design.efficacy);
    let (bq, bl) = (
        quadratic.design.futility.unwrap(),
        linear.design.futility.unwrap(),
    );
    // β spent sooner: higher bounds (earlier acceptance) at every look but the last,
    // where both meet the efficacy bound.
    for k in 0..9 {
        assert!(
            bl[k] > bq[k],
            "look {k}: linear {} vs quadratic {}",
            bl[k],
            bq[k]
        );
    }
    assert!((bl[9] - linear.design.efficacy[9]).abs() < 1e-12);
    assert!(matches!(
        Gate::for_study_with(
            100,
            0.05,
            &looks,
            &Spending::OBrienFleming,
            Some((0.1, 0.0))
        ),
        Err(GateError::FutilityRho(_))
    ));
}

#[test]
fn gate_overrides_win_over_the_spec_and_need_the_gate() {
    let spec = GateSettings {
        looks: Looks::RunCounts(vec![25, 50]),
        spending: Spending::Pocock,
        futility_beta: Some(0.1),
        futility_rho: 1.0,
    };
    // Nothing given: the spec's settings, or no gate without them.
    let none = GateOverrides::default();
    assert_eq!(none.apply(Some(&spec)), Ok(Some(spec.clone())));
    assert_eq!(none.apply(None), Ok(None));
    // `sequential` alone: the defaults.
    let on = GateOverrides {
        sequential: true,
        ..Default::default()
    };
    assert_eq!(on.apply(None), Ok(Some(GateSettings::default())));
    // Each given setting wins over the spec's key; the others stay the spec's.
    let looks = GateOverrides {
        looks: Some(Looks::Count(4)),
        futility_beta: Some(0.2),
        ..Default::default()
    };
    assert_eq!(
        looks.apply(Some(&spec)),
        Ok(Some(GateSettings {
            looks: Looks::Count(4),
            futility_beta: Some(0.2),
            ..spec.clone()
        }))
    );
    // A setting without a gate, and ρ without β, are refused naming the setting.
    assert_eq!(
        looks.apply(None),
        Err(GateOverrideError::NotSequential(GateSetting::Looks))
    );
    let spending = GateOverrides {
        spending: Some(Spending::Pocock),
        ..Default::default()
    };
    assert_eq!(
        spending.apply(None),
        Err(GateOverrideError::NotSequential(GateSetting::Spending))
    );
    let rho = GateOverrides {
        sequential: true,
        futility_rho: Some(1.0),
        ..Default::default()
    };
    assert_eq!(
        rho.apply(Some(&spec)),
        Err(GateOverrideError::RhoWithoutFutility)
    );
}
