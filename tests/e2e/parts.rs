//! Parts as users bring them: a part larger than the machine is refused at submission with its
//! sizes and the machine's, a mesh that cannot be read is refused naming where, and neither leaves
//! a job behind; the next good part is accepted.

use depthmill_geometry::Mesh;
use depthmill_tests::TestStack;
use nalgebra::Point3;
use serde_json::json;

/// A closed box mesh of `x` x `y` x `z` mm, corner at the origin, as binary STL.
fn box_stl(x: f64, y: f64, z: f64, header: &str) -> Vec<u8> {
    let vertices: Vec<Point3<f64>> = (0..8)
        .map(|k| {
            Point3::new(
                if k & 1 == 0 { 0.0 } else { x },
                if k & 2 == 0 { 0.0 } else { y },
                if k & 4 == 0 { 0.0 } else { z },
            )
        })
        .collect();
    let triangles = vec![
        [0, 2, 1],
        [1, 2, 3],
        [4, 5, 6],
        [5, 7, 6],
        [0, 1, 4],
        [1, 5, 4],
        [2, 6, 3],
        [3, 6, 7],
        [0, 4, 2],
        [2, 4, 6],
        [1, 3, 5],
        [3, 7, 5],
    ];
    let mut bytes = Vec::new();
    depthmill_geometry::formats::write_stl(&mut bytes, &Mesh { vertices, triangles }, header)
        .expect("writing to memory");
    bytes
}

async fn job_count(stack: &TestStack) -> anyhow::Result<usize> {
    let page: serde_json::Value =
        stack.http.get(stack.url("/v1/jobs?limit=100")).send().await?.json().await?;
    Ok(page["jobs"].as_array().map_or(0, Vec::len))
}

#[tokio::test]
async fn parts_the_machine_cannot_hold_or_files_that_cannot_be_read_are_refused_at_submission()
-> anyhow::Result<()> {
    let stack = TestStack::start().await?;

    // 250 mm long: the EMCO's X travel is 200 mm.
    let sha = stack.upload("model/stl", box_stl(250.0, 40.0, 10.0, "long bar")).await?;
    let (status, body) = stack.post_job(&json!({"input": {"kind": "mesh", "artifact": sha}}), None).await?;
    assert_eq!(status, 400, "{body}");
    assert_eq!(body["error"]["field"], "input", "{body}");
    let msg = body["error"]["message"].as_str().unwrap_or_default();
    assert!(msg.contains("250.0 x 40.0 x 10.0 mm") && msg.contains("200.0 x 100.0 x 200.0 mm"), "{msg}");

    // The same bar in inches is 6.35 m long; 3 x 3 x 0.5 inches fits once the job says so.
    let sha = stack.upload("model/stl", box_stl(3.0, 3.0, 0.5, "small block")).await?;
    let (status, body) =
        stack.post_job(&json!({"input": {"kind": "mesh", "artifact": sha, "units": "in"}, "execute": {"material": "wax"}}), None).await?;
    assert_eq!(status, 201, "{body}");
    let good_id = body["id"].as_str().unwrap_or_default().to_string();
    // ... and 10 x 10 x 1 inches does not.
    let sha = stack.upload("model/stl", box_stl(10.0, 10.0, 1.0, "plate")).await?;
    let (status, body) =
        stack.post_job(&json!({"input": {"kind": "mesh", "artifact": sha, "units": "in"}}), None).await?;
    assert_eq!(status, 400, "{body}");
    assert!(
        body["error"]["message"].as_str().unwrap_or_default().contains("254.0 x 254.0 x 25.4 mm"),
        "{body}"
    );

    // An ASCII STL with a coordinate that is not a number: refused naming the line, no job.
    let bad = b"solid bad\nfacet normal 0 0 1\n outer loop\n  vertex 0 0 0\n  vertex 10 0 0\n  vertex 0 ten 0\n endloop\nendfacet\nendsolid bad\n";
    let sha = stack.upload("model/stl", bad.to_vec()).await?;
    let (status, body) = stack.post_job(&json!({"input": {"kind": "mesh", "artifact": sha}}), None).await?;
    assert_eq!(status, 400, "{body}");
    assert_eq!(body["error"]["field"], "input.artifact", "{body}");
    assert!(body["error"]["message"].as_str().unwrap_or_default().contains("line 6"), "{body}");

    // An unknown material is the machine service's to refuse, named.
    let sha = stack.upload("model/stl", box_stl(20.0, 20.0, 5.0, "block")).await?;
    let (status, body) = stack
        .post_job(
            &json!({"input": {"kind": "mesh", "artifact": sha}, "execute": {"material": "cheese"}}),
            None,
        )
        .await?;
    assert_eq!(status, 400, "{body}");
    assert_eq!(body["error"]["field"], "execute.material", "{body}");

    // Only the good job exists.
    assert_eq!(job_count(&stack).await?, 1);
    assert_eq!(stack.get_job(&good_id).await?["id"], good_id.as_str());
    stack.http.post(stack.url(&format!("/v1/jobs/{good_id}/cancel"))).send().await?;
    stack.shutdown().await
}
