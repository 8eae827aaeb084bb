//! The anchors' re-basing when the calibration in use changes.

use super::*;

#[test]
fn a_changed_calibration_re_bases_the_offset_as_if_it_had_been_in_use_all_along() {
    use crate::evidence::calibration::{apply, regressors};
    // Two steps of the same drive: one tracker had θ* in use from the start, the other took it
    // only at the second step. Re-based, their offsets agree: the offset is what θ* makes of all
    // the motion behind the anchors (speed scale, heading and lag alike). Not re-based, the late
    // one keeps what the first step's uncorrected dead reckoning built.
    let theta = [0.05, 0.1, 0.3];
    let gnss = [[3.0, 12.0], [1.0, 9.0]];
    let motion = [[0.0, 10.0], [2.0, 8.0]];
    let velocity_change = [[1.0, -2.0], [0.5, 0.0]];
    let params = OffsetParams {
        noise_m2: [1e6; ANCHOR_COUNT],
        step_noise_m2: 1e6,
        rebase_on_calibration: true,
        ..unit_params()
    };
    let push = |tracker: &mut OffsetTracker, i: usize, theta: [f64; 3]| {
        let correction = apply(&regressors(motion[i], velocity_change[i]), &theta);
        tracker.push(&OffsetStep {
            residual: [
                gnss[i][0] - motion[i][0] + correction[0],
                gnss[i][1] - motion[i][1] + correction[1],
            ],
            motion: motion[i],
            velocity_change: velocity_change[i],
            theta_in_use: theta,
            calibrated: true,
            ..step([0.0; 2], 1.0)
        })
    };
    let run = |params: &OffsetParams, first: [f64; 3]| {
        let mut tracker = OffsetTracker::new(params);
        push(&mut tracker, 0, first);
        push(&mut tracker, 1, theta)
    };
    let all_along = run(&params, theta);
    let late = run(&params, [0.0; 3]);
    // By hand for the slow anchor (a = e^{−1/FOLLOW_S}): o = a·(a·r₁ + r₂) with r under θ*.
    let a = keep(1.0, ANCHOR_COUNT - 1);
    let r = |i: usize| {
        let c = apply(&regressors(motion[i], velocity_change[i]), &theta);
        [
            gnss[i][0] - motion[i][0] + c[0],
            gnss[i][1] - motion[i][1] + c[1],
        ]
    };
    for axis in 0..2 {
        let expected = a * (a * r(0)[axis] + r(1)[axis]);
        assert!(
            (all_along.offset_m[axis] - expected).abs() < 1e-12,
            "{all_along:?}"
        );
        assert!((late.offset_m[axis] - expected).abs() < 1e-12, "{late:?}");
    }
    let kept = run(
        &OffsetParams {
            rebase_on_calibration: false,
            ..params
        },
        [0.0; 3],
    );
    let first_correction = apply(&regressors(motion[0], velocity_change[0]), &theta);
    for (axis, correction) in first_correction.iter().enumerate() {
        let missing = a * a * correction;
        assert!((kept.offset_m[axis] - (all_along.offset_m[axis] - missing)).abs() < 1e-12);
    }
}
