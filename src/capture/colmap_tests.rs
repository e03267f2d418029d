use super::*;
use glam::{DMat3, Vec3};

fn model(cameras: &str, images: &str) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("cameras.txt"), cameras).unwrap();
    std::fs::write(dir.path().join("images.txt"), images).unwrap();
    dir
}

fn read_model(cameras: &str, images: &str) -> Result<Vec<CapturedView>> {
    let dir = model(cameras, images);
    read(dir.path(), Path::new("images"))
}

const HEADER: &str = "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n";

/// The convention, pinned by hand: the identity rotation with t = (0, 0, 5) puts the camera at
/// (0, 0, −5) looking along +z, its image's up along −y (OpenCV: +y is down the image).
#[test]
fn an_identity_pose_looks_along_plus_z_with_y_down() {
    // A byte-order mark first (as some Windows tools write), and a name with two spaces.
    let cameras = format!("\u{feff}{HEADER}1 PINHOLE 20 10 100 50 12 3\n");
    let images = "# Image list\n7 1 0 0 0 0 0 5 1 frame  7.png\n\n";
    let views = read_model(&cameras, images).unwrap();
    let c = views[0].camera;
    assert_eq!(c.position, Vec3::new(0.0, 0.0, -5.0));
    assert!((c.direction(12.0, 3.0) - Vec3::Z).length() < 1e-6);
    let below = c.direction(12.0, 4.0);
    assert!((below.y / below.z - 0.02).abs() < 1e-6, "{below}");
    let right = c.direction(13.0, 3.0);
    assert!((right.x / right.z - 0.01).abs() < 1e-6, "{right}");
    assert_eq!(
        views[0].image.as_deref(),
        Some(Path::new("images/frame  7.png"))
    );
    // The same rotation at any length: its length overflowed at 1e200, and 1e-200 was "zero".
    for w in ["1e200", "1e-200"] {
        let images = format!("7 {w} 0 0 0 0 0 5 1 a.png\n\n");
        let same = read_model(&cameras, &images).unwrap()[0].camera;
        assert_eq!(same.direction(12.0, 4.0), below, "{w}");
    }
}

/// The same cameras written as COLMAP poses and as a transforms.json (OpenGL axes) see the same
/// rays: the two readers agree on every convention they share.
#[test]
fn colmap_and_transforms_agree_on_the_same_cameras() {
    let dir = tempfile::tempdir().unwrap();
    let mut images = String::new();
    let mut frames = Vec::new();
    let positions = [
        Vec3::new(3.0, 1.0, 9.0),
        Vec3::new(-7.0, 4.0, -2.0),
        Vec3::new(0.5, -6.0, 1.0),
    ];
    for (i, &p) in positions.iter().enumerate() {
        let rows = crate::capture::transforms::camera_to_world(p, Vec3::ZERO, Vec3::Y);
        frames.push(format!(r#"{{ "transform_matrix": {rows:?} }}"#));
        let m = DMat3::from_cols_array_2d(&[
            [rows[0][0], rows[1][0], rows[2][0]].map(f64::from),
            [-rows[0][1], -rows[1][1], -rows[2][1]].map(f64::from),
            [-rows[0][2], -rows[1][2], -rows[2][2]].map(f64::from),
        ]);
        let world_to_camera = m.transpose();
        let q = DQuat::from_mat3(&world_to_camera);
        let t = -(world_to_camera * p.as_dvec3());
        images += &format!(
            "{i} {} {} {} {} {} {} {} 1 {i}.png\n\n",
            q.w, q.x, q.y, q.z, t.x, t.y, t.z
        );
    }
    let json = format!(
        r#"{{ "fl_x": 40, "fl_y": 44, "cx": 15, "cy": 11, "w": 32, "h": 24, "frames": [{}] }}"#,
        frames.join(", ")
    );
    std::fs::write(dir.path().join("transforms.json"), json).unwrap();
    let from_json = crate::capture::transforms::read(&dir.path().join("transforms.json")).unwrap();
    let from_colmap = read_model("1 PINHOLE 32 24 40 44 15 11\n", &images).unwrap();
    for (a, b) in from_json.iter().zip(&from_colmap) {
        assert!((a.camera.position - b.camera.position).length() < 1e-5);
        for (x, y) in [(0.0, 0.0), (15.0, 11.0), (31.5, 2.0), (4.0, 23.0)] {
            let (da, db) = (a.camera.direction(x, y), b.camera.direction(x, y));
            assert!((da - db).length() < 1e-5, "{x},{y}: {da} {db}");
        }
    }
}

#[test]
fn what_is_not_a_pinhole_or_not_colmap_is_refused_naming_the_line() {
    let pose = "1 1 0 0 0 0 0 5 1 a.png\n";
    for (cameras, images, needle) in [
        ("1 OPENCV 8 8 10 10 4 4 0.1 0 0 0\n", pose, "distortion 0.1"),
        (
            "1 SIMPLE_RADIAL 8 8 10 4 4 -0.02\n",
            pose,
            "distortion -0.02",
        ),
        ("1 FISHEYE 8 8 10 4 4\n", pose, "not one volgrad reads"),
        ("1 pinhole 8 8 10 10 4 4\n", pose, "in capitals"),
        ("1 PINHOLE 8 8 10 10 4\n", pose, "too few"),
        ("-1 PINHOLE 8 8 10 10 4 4\n", pose, "'-1' is not an id"),
        ("1 PINHOLE 8 8 10 10 4 4 1\n", pose, "takes 4 parameters"),
        ("1 PINHOLE 0 8 10 10 4 4\n", pose, "at least 1"),
        ("1 PINHOLE 65536 65536 10 10 4 4\n", pose, "too large"),
        ("1 PINHOLE 8 8 0 10 4 4\n", pose, "fx"),
        ("1 PINHOLE 8 8 nan 10 4 4\n", pose, "not a finite number"),
        (
            "1 PINHOLE 8 8 1 1 1e20 1e20\n",
            pose,
            "focal lengths from the view direction",
        ),
        (
            "1 PINHOLE 8 8 10 10 4 4\n1 PINHOLE 8 8 10 10 4 4\n",
            pose,
            "defined twice",
        ),
        ("# nothing\n", pose, "no cameras"),
        (
            "1 PINHOLE 8 8 10 10 4 4\n",
            "1 1 0 0 0 0 0 5 2 a.png\n",
            "camera 2",
        ),
        (
            "1 PINHOLE 8 8 10 10 4 4\n",
            "1 0 0 0 0 0 0 5 1 a.png\n",
            "quaternion is zero",
        ),
        (
            "1 PINHOLE 8 8 10 10 4 4\n",
            "1 1 0 0 0 0 0 1e30 1 a.png\n",
            "within",
        ),
        (
            "1 PINHOLE 8 8 10 10 4 4\n",
            "1 1 0 0 0 5 1 a.png\n",
            "IMAGE_ID QW",
        ),
        (
            "1 PINHOLE 8 8 10 10 4 4\n",
            "# only comments\n",
            "no images",
        ),
        // Without the POINTS2D lines the second image's line would be taken for the first's
        // points, and every other image dropped.
        (
            "1 PINHOLE 8 8 10 10 4 4\n",
            "1 1 0 0 0 0 0 5 1 a.png\n2 1 0 0 0 0 0 6 1 b.png\n",
            "POINTS2D",
        ),
        (
            "1 PINHOLE 8 8 10 10 4 4\n",
            "1 1 0 0 0 0 0 5 1 a.png\n2.5 3 x\n",
            "POINT3D_ID",
        ),
        (
            "1 PINHOLE 8 8 10 10 4 4\n",
            "1 1 0 0 0 0 0 5 1 a.png\n\n1 1 0 0 0 0 0 6 1 b.png\n",
            "image 1 is listed twice",
        ),
        (
            "1 PINHOLE 8 8 10 10 4 4\n",
            "1 1 0 0 0 0 0 5 1 a.png\n\n2 1 0 0 0 0 0 6 1 a.png\n",
            "line 1 and line 3 name the same image",
        ),
        ("1 PINHOLE 8 8 1e-30 10 4 4\n", pose, "180°"),
    ] {
        let err = format!("{:#}", read_model(cameras, images).err().expect(needle));
        assert!(err.contains(needle), "{needle}: {err}");
        assert!(err.contains("line") || needle.starts_with("no "), "{err}");
        // Each error names the file it is in.
        let file = if images == pose {
            "cameras.txt"
        } else {
            "images.txt"
        };
        assert!(err.contains(file), "{needle}: {err}");
    }
    // Points after each image, some of them without a 3D point (−1), are read past.
    let points = "1 1 0 0 0 0 0 5 1 a.png\n2.5 3.5 -1 4 4 17\n2 1 0 0 0 0 0 6 1 b.png\n\n";
    assert_eq!(
        read_model("1 PINHOLE 8 8 10 10 4 4\n", points)
            .unwrap()
            .len(),
        2
    );
    let dir = tempfile::tempdir().unwrap();
    let err = format!("{:#}", read(dir.path(), dir.path()).err().unwrap());
    assert!(err.contains("cameras.txt"), "{err}");
    // COLMAP's binary model, as its mapper writes it, is named with the conversion.
    for name in ["cameras.bin", "images.bin"] {
        std::fs::write(dir.path().join(name), [0u8; 8]).unwrap();
    }
    let err = format!("{:#}", read(dir.path(), dir.path()).err().unwrap());
    assert!(
        err.contains("binary COLMAP model") && err.contains("--output_type TXT"),
        "{err}"
    );
}

/// Without `images`, a model's pictures are beside its `sparse` folder: the project's originals
/// for `P/sparse/0`, the undistorted ones `image_undistorter` writes beside `P/dense/sparse`.
#[test]
fn the_default_images_folder_follows_colmaps_layout() {
    assert_eq!(
        default_images(Path::new("P/sparse/0")),
        Path::new("P/images")
    );
    assert_eq!(
        default_images(Path::new("P/dense/sparse")),
        Path::new("P/dense/images")
    );
    assert_eq!(default_images(Path::new("P/model")), Path::new("P/images"));
}
