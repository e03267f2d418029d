//! The command line as clap sees it: well-formed, and flags parsed into the library's types.

use crate::{Cli, Command};
use clap::CommandFactory;
use clap::Parser;

#[test]
fn the_command_line_is_well_formed() {
    Cli::command().debug_assert();
}

#[test]
fn flags_parse_into_the_library_types() {
    use volgrad::gradient::adjoint::Estimator;
    use volgrad::gradient::loss::Loss;
    let parse = |line: &str| Cli::try_parse_from(line.split_whitespace());
    match parse("volgrad grad s.toml --estimator fd --loss relative-l2")
        .unwrap()
        .command
    {
        Command::Grad(a) => {
            assert!(a.estimator == crate::cli::grad::Method::FiniteDifferences);
            assert_eq!(a.loss, Loss::RelativeL2);
        }
        _ => panic!("not grad"),
    }
    match parse("volgrad grad s.toml --estimator drt")
        .unwrap()
        .command
    {
        Command::Grad(a) => {
            assert!(a.estimator == crate::cli::grad::Method::Estimator(Estimator::Drt))
        }
        _ => panic!("not grad"),
    }
    match parse("volgrad compare s.toml --estimators drt,joint --budget 2m")
        .unwrap()
        .command
    {
        Command::Compare(a) => {
            assert_eq!(a.estimators, [Estimator::Drt, Estimator::Joint]);
            assert_eq!(a.budget, Some(std::time::Duration::from_secs(120)));
        }
        _ => panic!("not compare"),
    }
    // fd is a grad method, not an estimator that compare or gradcheck could run.
    assert!(parse("volgrad compare s.toml --estimators fd").is_err());
    assert!(parse("volgrad gradcheck s.toml --estimator fd").is_err());
    assert!(parse("volgrad compare s.toml --budget 3 fortnights").is_err());
    assert!(parse("volgrad render s.toml --majorant sparse").is_err());
}

/// A finite-difference step is judged against the grid it changes: 1e-5 resolves beside an
/// albedo grid's values (at most 1) but not beside a density of 50, where f32's rounding is as
/// large as the step.
#[test]
fn a_step_is_judged_against_the_grid_it_changes() {
    use glam::IVec3;
    use volgrad::gradient::loss::Loss;
    use volgrad::volume::brickmap::BrickMapBuilder;
    let grid = |value: f32| {
        let mut b = BrickMapBuilder::new();
        b.set(IVec3::ZERO, value, true);
        b.build()
    };
    let fd = super::FdArgs {
        eps: Some(1e-5),
        fd_spp: 1,
        repeats: 2,
    };
    assert!(fd.options(&grid(1.0), Loss::Mean, 1, 4).is_ok());
    let e = fd.options(&grid(50.0), Loss::Mean, 1, 4).unwrap_err();
    assert!(e.to_string().contains("f32 resolves"), "{e}");
}
