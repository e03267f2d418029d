use super::*;

const IDENTITY_AT_5: &str =
    r#"{ "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]] }"#;

fn read_json(json: &str) -> Result<Vec<CapturedView>> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("transforms.json");
    std::fs::write(&path, json).unwrap();
    read(&path)
}

fn error_of(json: &str) -> String {
    match read_json(json) {
        Ok(_) => panic!("accepted: {json}"),
        Err(e) => format!("{e:#}"),
    }
}

/// The convention, pinned by a matrix written by hand: the identity rotation at (0, 0, 5)
/// looks down −z with +y up and +x to the right, as a Blender or OpenGL camera does.
#[test]
fn an_identity_camera_looks_down_minus_z() {
    let json =
        format!(r#"{{ "camera_angle_x": 0.5, "w": 20, "h": 10, "frames": [{IDENTITY_AT_5}] }}"#);
    let camera = read_json(&json).unwrap()[0].camera;
    assert_eq!(camera.position, Vec3::new(0.0, 0.0, 5.0));
    assert!((camera.direction(10.0, 5.0) - Vec3::NEG_Z).length() < 1e-6);
    assert!(camera.direction(10.0, 0.0).y > 0.0, "the top row looks up");
    assert!(
        camera.direction(20.0, 5.0).x > 0.0,
        "the right column looks right"
    );
    // The horizontal field of view is camera_angle_x: the right edge is 0.25 rad off-axis.
    let edge = camera.direction(20.0, 5.0);
    assert!((edge.x.atan2(-edge.z) - 0.25).abs() < 1e-5);
    let m = camera_to_world(Vec3::new(0.0, 0.0, 5.0), Vec3::ZERO, Vec3::Y);
    assert_eq!(
        m,
        [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 5.0],
            [0.0, 0.0, 0.0, 1.0]
        ]
    );
}

/// fl_x, fl_y, cx and cy are used, not dropped: the principal point is where the camera looks,
/// and one pixel away from it is 1/fx (1/fy) radians off-axis; a frame's own values win.
#[test]
fn full_pinhole_intrinsics_are_applied_per_file_and_per_frame() {
    let json = format!(
        r#"{{ "fl_x": 100, "fl_y": 50, "cx": 12, "cy": 3, "w": 20, "h": 10,
            "frames": [{IDENTITY_AT_5}, {{ "fl_x": 40, "cx": 10, "cy": 5,
            "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]] }}] }}"#
    );
    let views = read_json(&json).unwrap();
    let c = views[0].camera;
    assert!((c.direction(12.0, 3.0) - Vec3::NEG_Z).length() < 1e-6);
    let right = c.direction(13.0, 3.0);
    assert!((right.x / -right.z - 0.01).abs() < 1e-6, "{right}");
    let up = c.direction(12.0, 2.0);
    assert!((up.y / -up.z - 0.02).abs() < 1e-6, "{up}");
    let f = views[1].camera;
    assert!((f.direction(10.0, 5.0) - Vec3::NEG_Z).length() < 1e-6);
    let right = f.direction(11.0, 5.0);
    assert!((right.x / -right.z - 0.025).abs() < 1e-6, "{right}");
    let up = f.direction(10.0, 4.0);
    assert!((up.y / -up.z - 0.02).abs() < 1e-6, "fy is the file's: {up}");
}

/// instant-ngp's `scale` and `offset` map positions (p ↦ scale·p + offset); directions keep.
#[test]
fn scale_and_offset_move_the_cameras() {
    let json = format!(
        r#"{{ "camera_angle_x": 0.5, "w": 8, "h": 8, "scale": 0.5, "offset": [1, 2, 3],
            "aabb_scale": 4, "frames": [{IDENTITY_AT_5}] }}"#
    );
    let camera = read_json(&json).unwrap()[0].camera;
    assert_eq!(camera.position, Vec3::new(1.0, 2.0, 5.5));
    assert!((camera.direction(4.0, 4.0) - Vec3::NEG_Z).length() < 1e-6);
}

/// A camera far away keeps its direction: the frame is read in f64 and the camera built from
/// its direction, not from a target that rounds onto the position.
#[test]
fn a_distant_camera_keeps_its_direction() {
    let json = r#"{ "camera_angle_x": 0.5, "w": 8, "h": 8, "frames": [{ "transform_matrix":
        [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1e8], [0, 0, 0, 1]] }] }"#;
    let camera = read_json(json).unwrap()[0].camera;
    assert!((camera.direction(4.0, 4.0) - Vec3::NEG_Z).length() < 1e-6);
    // Axes of length 1e30 (a uniform scale f32 could not square) give the same camera at z = 5.
    let json = r#"{ "camera_angle_x": 0.5, "w": 8, "h": 8, "frames": [{ "transform_matrix":
        [[1e30, 0, 0, 0], [0, 1e30, 0, 0], [0, 0, 1e30, 5], [0, 0, 0, 1]] }] }"#;
    let camera = read_json(json).unwrap()[0].camera;
    assert!((camera.direction(4.0, 4.0) - Vec3::NEG_Z).length() < 1e-6);
    assert_eq!(camera.position, Vec3::new(0.0, 0.0, 5.0));
}

#[test]
fn what_a_pinhole_cannot_be_is_refused_naming_the_key() {
    let with = |keys: &str| {
        format!(
            r#"{{ "camera_angle_x": 0.5, "w": 8, "h": 8, {keys} "frames": [{IDENTITY_AT_5}] }}"#
        )
    };
    let sized =
        |keys: &str| format!(r#"{{ "camera_angle_x": 0.5, {keys} "frames": [{IDENTITY_AT_5}] }}"#);
    let matrix = |rows: &str| {
        format!(
            r#"{{ "camera_angle_x": 0.5, "w": 8, "h": 8, "frames": [{{ "transform_matrix": {rows} }}] }}"#
        )
    };
    for (json, needle) in [
        (with(r#""k1": 0.01,"#), "k1 = 0.01"),
        (with(r#""k1": 1e-300,"#), "k1 = 1e-300:"),
        (with(r#""p2": -0.001,"#), "p2"),
        (
            with(r#""camera_model": "OPENCV_FISHEYE","#),
            "not a pinhole",
        ),
        (with(r#""is_fisheye": true,"#), "is_fisheye"),
        (with(r#""fl_x": 30,"#), "disagree"),
        (with(r#""camera_angle_y": 4,"#), "camera_angle_y"),
        (with(r#""fl_y": 0,"#), "fy"),
        (
            sized(r#""fl_x": 1e-300, "w": 8, "h": 8,"#),
            "fl_x = 1e-300: the focal length fx",
        ),
        (
            sized(r#""fl_x": 1e300, "w": 8, "h": 8,"#),
            "fl_x = 1e300: the focal length fx",
        ),
        (with(r#""cx": 1e40,"#), "principal point"),
        // Finite, but every ray's direction overflowed to the zero vector.
        (
            with(r#""cx": 1e20,"#),
            "focal lengths from the view direction",
        ),
        (with(r#""scale": 0,"#), "scale"),
        (with(r#""frobnicate": 1,"#), "unknown key \"frobnicate\""),
        // serde_json would keep the second.
        (with(r#""w": 8,"#), "\"w\" is given twice"),
        (sized(r#""w": 65536, "h": 65536,"#), "too large"),
        (
            sized(r#""w": 0, "h": 8,"#),
            "w = 0 is not a whole number of pixels ≥ 1",
        ),
        (
            r#"{ "camera_angle_x": 0.5, "w": 8, "h": 8, "frames": [] }"#.to_string(),
            "empty",
        ),
        (
            format!(r#"{{ "w": 8, "h": 8, "frames": [{IDENTITY_AT_5}] }}"#),
            "focal length is unknown",
        ),
        (
            format!(r#"{{ "camera_angle_x": 0.5, "frames": [{IDENTITY_AT_5}] }}"#),
            "size is unknown",
        ),
        (
            matrix("[[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 5], [0, 0, 0, 1]]"),
            "degenerate",
        ),
        (
            matrix("[[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]]"),
            "left-handed",
        ),
        (
            matrix("[[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]]"),
            "orthogonal",
        ),
        (
            matrix("[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 1, 1]]"),
            "last row",
        ),
        (
            matrix("[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]]"),
            "unequally",
        ),
        (
            matrix("[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1e30], [0, 0, 0, 1]]"),
            "within",
        ),
        ("{ not json".to_string(), "not a transforms.json"),
    ] {
        let err = error_of(&json);
        assert!(err.contains(needle), "{needle}: {err}");
    }
    // A frame's unknown key is named with its frame.
    let json =
        r#"{ "camera_angle_x": 0.5, "w": 8, "h": 8, "frames": [{ "transform_matrx": [] }] }"#;
    assert!(error_of(json).contains("frames[0]: unknown key \"transform_matrx\""));
}

/// A value of the wrong type is named by its key and frame, not only by its type.
#[test]
fn a_value_of_the_wrong_type_is_named_by_its_path() {
    let file = |top: &str, second_frame: &str| {
        format!(
            r#"{{ "camera_angle_x": 0.5, "h": 8, {top} "frames": [{IDENTITY_AT_5}, {second_frame}] }}"#
        )
    };
    let rows =
        |last: &str| format!(r#"[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, {last}]]"#);
    let matrix = |last: &str| format!(r#"{{ "transform_matrix": {} }}"#, rows(last));
    for (json, needle) in [
        (
            file(r#""w": "8","#, &matrix("1")),
            "the top level: w must be a number (got \"8\")",
        ),
        (
            file(
                r#""w": 8,"#,
                &format!(r#"{{ "fl_x": true, "transform_matrix": {} }}"#, rows("1")),
            ),
            "frames[1]: fl_x must be a number (got true)",
        ),
        (
            file(r#""w": 8,"#, &matrix("\"1\"")),
            "frames[1].transform_matrix[3][3]: invalid type: string \"1\", expected f64",
        ),
        (
            file(
                r#""w": 8,"#,
                &format!(r#"{{ "file_path": 5, "transform_matrix": {} }}"#, rows("1")),
            ),
            "frames[1].file_path: invalid type: integer `5`",
        ),
        (
            file(r#""w": 8, "scale": [2],"#, &matrix("1")),
            "scale: invalid type: sequence",
        ),
    ] {
        let err = error_of(&json);
        assert!(err.contains(needle), "{needle}: {err}");
    }
}

#[test]
fn two_frames_of_one_image_are_refused() {
    let frame = |name: &str| {
        format!(
            r#"{{ "file_path": "{name}", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]] }}"#
        )
    };
    let json = |a: &str, b: &str| {
        format!(
            r#"{{ "camera_angle_x": 0.7, "w": 8, "h": 8, "frames": [{}, {}] }}"#,
            frame(a),
            frame(b)
        )
    };
    assert!(read_json(&json("a.png", "b.png")).is_ok());
    let error = error_of(&json("a.png", "a.png"));
    assert!(
        error.contains("frames[0] and frames[1] name the same image"),
        "{error}"
    );
}

/// A file_path without an extension is looked for as .exr, then .png; when neither is there the
/// error names both files it looked for. An empty one is refused as such.
#[test]
fn an_image_without_an_extension_is_looked_for_as_exr_then_png() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("b.png"), b"").unwrap();
    std::fs::write(d.join("b.exr"), b"").unwrap();
    assert_eq!(image_path(d, "b").unwrap(), d.join("b.exr"));
    std::fs::remove_file(d.join("b.exr")).unwrap();
    assert_eq!(image_path(d, "b").unwrap(), d.join("b.png"));
    assert_eq!(image_path(d, "c.jpg").unwrap(), d.join("c.jpg"));
    let error = image_path(d, "a").unwrap_err().to_string();
    assert!(error.contains("'a' has no extension"), "{error}");
    assert!(
        error.contains("a.exr") && error.contains("a.png"),
        "{error}"
    );
    // An empty name is said to be one, not looked for as '.exr' and '.png'.
    let error = image_path(d, "").unwrap_err().to_string();
    assert_eq!(error, "file_path is empty: it names the frame's picture");
}

/// instant-ngp's `colmap2nerf.py` writes the size as decimals ("w": 20.0): a whole number is
/// read whatever its notation; a fraction of a pixel, or a width without a height, is refused.
#[test]
fn sizes_are_whole_numbers_in_any_notation_and_come_in_pairs() {
    let with =
        |size: &str| format!(r#"{{ "camera_angle_x": 0.5, {size}, "frames": [{IDENTITY_AT_5}] }}"#);
    let camera = read_json(&with(r#""w": 20.0, "h": 10.0"#)).unwrap()[0].camera;
    assert_eq!((camera.width, camera.height), (20, 10));
    for (size, says) in [
        (r#""w": 20.5, "h": 10"#, "w = 20.5 is not a whole number"),
        (
            r#""w": 1e10, "h": 10"#,
            "w = 10000000000 pixels is too large",
        ),
        (
            r#""w": 20, "h": -10"#,
            "h = -10 is not a whole number of pixels ≥ 1",
        ),
        (r#""w": 20"#, "`w` without `h`"),
        (r#""h": 10"#, "`h` without `w`"),
    ] {
        let e = error_of(&with(size));
        assert!(e.contains(says), "{size}: {e}");
    }
}

/// A frame's focal length replaces the top level's whichever way each gives it (a frame's
/// `fl_x` against the top's `camera_angle_x` is not a disagreement), and a frame's size replaces
/// the top's as a pair.
#[test]
fn a_frames_focal_length_and_size_replace_the_top_levels_as_units() {
    let json = r#"{ "camera_angle_x": 0.5, "w": 20, "h": 10, "frames": [{ "fl_x": 40, "w": 30, "h": 15,
            "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]] }] }"#;
    let c = read_json(json).unwrap()[0].camera;
    assert_eq!((c.width, c.height), (30, 15));
    // One pixel right of the centre is 1/40 rad off-axis: fx = 40, not 20 / (2·tan 0.25).
    let d = c.direction(16.0, 7.5);
    assert!((d.x.atan2(-d.z) - (1.0f32 / 40.0).atan()).abs() < 1e-5);
    // The other way round: a frame's angle replaces the top's focal length.
    let json = r#"{ "fl_x": 40, "w": 20, "h": 10, "frames": [{ "camera_angle_x": 0.5,
            "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]] }] }"#;
    let edge = read_json(json).unwrap()[0].camera.direction(20.0, 5.0);
    assert!((edge.x.atan2(-edge.z) - 0.25).abs() < 1e-5);
}
