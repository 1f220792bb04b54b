//! The built-in registry describes itself consistently: one check over every stage that
//! `pipe` ships (ids, docs, parameter words and units, declaration = defaults, ports).

#[test]
fn every_builtin_stage_describes_itself_consistently() {
    let r = grainpipe_cli::builtin_registry();
    r.check_consistency().unwrap();
    // Every stage has at least one output, and every parameter default validates against
    // the parameter's own schema type (numbers where numbers are declared, and so on).
    for x in r.stages() {
        let info = x.stage.info();
        assert!(!info.outputs.is_empty(), "{} has no outputs", info.id);
        for p in &info.params {
            let t = p.schema.get("type").and_then(|t| t.as_str());
            let ok = match (t, &p.default) {
                (Some("number"), v) => v.is_number(),
                (Some("integer"), v) => v.is_u64() || v.is_i64(),
                (Some("boolean"), v) => v.is_boolean(),
                (Some("string"), v) => v.is_string(),
                (Some("array"), v) => v.is_array(),
                (Some("object"), v) => v.is_object(),
                _ => true,
            };
            assert!(
                ok,
                "{}.{}: default {} is not a {t:?}",
                info.id, p.name, p.default
            );
        }
    }
}
