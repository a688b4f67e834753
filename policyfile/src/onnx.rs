//! ONNX export of a state-based policy's deterministic actor, for flight stacks and companion
//! computers that run ONNX Runtime or TensorRT instead of dronerace.
//!
//! The graph takes `observation` `[batch, n]` in raw units (the policy's observation frame;
//! n = SPEC §5's 40 plus the racing-line points the policy reads)
//! and returns `action` `[batch, 4]`: the normaliser in double precision exactly as
//! [`ObsNormalizer::normalize`](crate::ObsNormalizer::normalize) computes it (cast, subtract
//! the mean, divide by `sqrt(var + epsilon)`, clip, cast back), then the actor's layers as `Gemm`
//! + `LeakyRelu`, then the clip to [-1, 1] that evaluation applies. Opset 13, IR version 7.
//!
//! The messages below are the subset of `onnx.proto` (the ONNX project's protobuf schema) this
//! export writes, with the schema's field numbers, so prost encodes a standard model file.

use prost::Message;

use crate::architecture::Agent;
use crate::blob::{BlobError, WeightsBlob};

/// ONNX opset the graph uses.
const OPSET: i64 = 13;
/// ONNX IR version of the file (ONNX 1.7+ reads it).
const IR_VERSION: i64 = 7;
/// `TensorProto.DataType` codes.
const FLOAT: i32 = 1;
const DOUBLE: i32 = 11;
/// `AttributeProto.AttributeType` codes.
const ATTRIBUTE_FLOAT: i32 = 1;
const ATTRIBUTE_INT: i32 = 2;

#[derive(Clone, PartialEq, Message)]
struct ModelProto {
    #[prost(int64, tag = "1")]
    ir_version: i64,
    #[prost(string, tag = "2")]
    producer_name: String,
    #[prost(string, tag = "3")]
    producer_version: String,
    #[prost(string, tag = "6")]
    doc_string: String,
    #[prost(message, optional, tag = "7")]
    graph: Option<GraphProto>,
    #[prost(message, repeated, tag = "8")]
    opset_import: Vec<OperatorSetIdProto>,
}

#[derive(Clone, PartialEq, Message)]
struct OperatorSetIdProto {
    #[prost(string, tag = "1")]
    domain: String,
    #[prost(int64, tag = "2")]
    version: i64,
}

#[derive(Clone, PartialEq, Message)]
struct GraphProto {
    #[prost(message, repeated, tag = "1")]
    node: Vec<NodeProto>,
    #[prost(string, tag = "2")]
    name: String,
    #[prost(message, repeated, tag = "5")]
    initializer: Vec<TensorProto>,
    #[prost(message, repeated, tag = "11")]
    input: Vec<ValueInfoProto>,
    #[prost(message, repeated, tag = "12")]
    output: Vec<ValueInfoProto>,
}

#[derive(Clone, PartialEq, Message)]
struct NodeProto {
    #[prost(string, repeated, tag = "1")]
    input: Vec<String>,
    #[prost(string, repeated, tag = "2")]
    output: Vec<String>,
    #[prost(string, tag = "3")]
    name: String,
    #[prost(string, tag = "4")]
    op_type: String,
    #[prost(message, repeated, tag = "5")]
    attribute: Vec<AttributeProto>,
}

#[derive(Clone, PartialEq, Message)]
struct AttributeProto {
    #[prost(string, tag = "1")]
    name: String,
    #[prost(float, tag = "2")]
    f: f32,
    #[prost(int64, tag = "3")]
    i: i64,
    #[prost(int32, tag = "20")]
    r#type: i32,
}

#[derive(Clone, PartialEq, Message)]
struct TensorProto {
    #[prost(int64, repeated, tag = "1")]
    dims: Vec<i64>,
    #[prost(int32, tag = "2")]
    data_type: i32,
    #[prost(string, tag = "8")]
    name: String,
    #[prost(bytes = "vec", tag = "9")]
    raw_data: Vec<u8>,
}

#[derive(Clone, PartialEq, Message)]
struct ValueInfoProto {
    #[prost(string, tag = "1")]
    name: String,
    #[prost(message, optional, tag = "2")]
    r#type: Option<TypeProto>,
}

#[derive(Clone, PartialEq, Message)]
struct TypeProto {
    #[prost(message, optional, tag = "1")]
    tensor_type: Option<TensorTypeProto>,
}

#[derive(Clone, PartialEq, Message)]
struct TensorTypeProto {
    #[prost(int32, tag = "1")]
    elem_type: i32,
    #[prost(message, optional, tag = "2")]
    shape: Option<TensorShapeProto>,
}

#[derive(Clone, PartialEq, Message)]
struct TensorShapeProto {
    #[prost(message, repeated, tag = "1")]
    dim: Vec<Dimension>,
}

#[derive(Clone, PartialEq, Message)]
struct Dimension {
    #[prost(int64, optional, tag = "1")]
    dim_value: Option<i64>,
    #[prost(string, optional, tag = "2")]
    dim_param: Option<String>,
}

/// A float tensor `[batch, width]` graph input or output.
fn batch_of(name: &str, width: usize) -> ValueInfoProto {
    let dims =
        vec![Dimension { dim_value: None, dim_param: Some("batch".into()) }, Dimension { dim_value: Some(width as i64), dim_param: None }];
    ValueInfoProto {
        name: name.into(),
        r#type: Some(TypeProto { tensor_type: Some(TensorTypeProto { elem_type: FLOAT, shape: Some(TensorShapeProto { dim: dims }) }) }),
    }
}

fn floats(name: &str, dims: &[usize], values: &[f32]) -> TensorProto {
    TensorProto {
        dims: dims.iter().map(|&d| d as i64).collect(),
        data_type: FLOAT,
        name: name.into(),
        raw_data: values.iter().flat_map(|v| v.to_le_bytes()).collect(),
    }
}

fn doubles(name: &str, dims: &[usize], values: &[f64]) -> TensorProto {
    TensorProto {
        dims: dims.iter().map(|&d| d as i64).collect(),
        data_type: DOUBLE,
        name: name.into(),
        raw_data: values.iter().flat_map(|v| v.to_le_bytes()).collect(),
    }
}

fn node(op: &str, inputs: &[&str], output: &str, attribute: Vec<AttributeProto>) -> NodeProto {
    NodeProto {
        input: inputs.iter().map(|s| s.to_string()).collect(),
        output: vec![output.into()],
        name: output.into(),
        op_type: op.into(),
        attribute,
    }
}

fn int_attribute(name: &str, i: i64) -> AttributeProto {
    AttributeProto { name: name.into(), f: 0.0, i, r#type: ATTRIBUTE_INT }
}

/// The deterministic actor of a state-based policy blob as an ONNX model file (a vision
/// policy is refused).
pub fn actor_model(blob: &WeightsBlob) -> Result<Vec<u8>, BlobError> {
    blob.check_agent(Agent::State)?;
    let arch = &blob.architecture;
    let n = &blob.normalizer;
    let inputs = arch.observation_dim;
    let std: Vec<f64> = n.var[..inputs].iter().map(|v| (v + n.epsilon).sqrt()).collect();
    let mut initializer = vec![
        doubles("obs_mean", &[inputs], &n.mean[..inputs]),
        doubles("obs_std", &[inputs], &std),
        doubles("obs_clip_low", &[], &[-n.clip]),
        doubles("obs_clip_high", &[], &[n.clip]),
        floats("action_low", &[], &[-1.0]),
        floats("action_high", &[], &[1.0]),
    ];
    let mut nodes = vec![
        node("Cast", &["observation"], "observation_f64", vec![int_attribute("to", i64::from(DOUBLE))]),
        node("Sub", &["observation_f64", "obs_mean"], "centred", vec![]),
        node("Div", &["centred", "obs_std"], "scaled", vec![]),
        node("Clip", &["scaled", "obs_clip_low", "obs_clip_high"], "normalized_f64", vec![]),
        node("Cast", &["normalized_f64"], "x0", vec![int_attribute("to", i64::from(FLOAT))]),
    ];
    // The actor's layers are the blob's first (weight, bias) pairs (export order).
    let layers = arch.hidden.len() + 1;
    let mut x = "x0".to_string();
    for (i, pair) in blob.params[..2 * layers].chunks(2).enumerate() {
        let (w, b) = (format!("actor_{i}_weight"), format!("actor_{i}_bias"));
        initializer.push(floats(&w, &pair[0].shape, &pair[0].values));
        initializer.push(floats(&b, &pair[1].shape, &pair[1].values));
        let z = format!("z{i}");
        nodes.push(node("Gemm", &[&x, &w, &b], &z, vec![]));
        x = if i + 1 < layers {
            let h = format!("x{}", i + 1);
            let alpha = AttributeProto { name: "alpha".into(), f: arch.negative_slope as f32, i: 0, r#type: ATTRIBUTE_FLOAT };
            nodes.push(node("LeakyRelu", &[&z], &h, vec![alpha]));
            h
        } else {
            z
        };
    }
    nodes.push(node("Clip", &[&x, "action_low", "action_high"], "action", vec![]));
    let graph = GraphProto {
        node: nodes,
        name: "dronerace_actor".into(),
        initializer,
        input: vec![batch_of("observation", inputs)],
        output: vec![batch_of("action", arch.action_dim)],
    };
    Ok(ModelProto {
        ir_version: IR_VERSION,
        producer_name: "dronerace".into(),
        producer_version: env!("CARGO_PKG_VERSION").into(),
        doc_string: format!("dronerace policy v{}: {} -> mean action in [-1, 1]", blob.version, arch.observation.describe()),
        graph: Some(graph),
        opset_import: vec![OperatorSetIdProto { domain: String::new(), version: OPSET }],
    }
    .encode_to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_blobs::pattern_blob;
    use crate::{Architecture, ObsNormalizer};

    /// Width of the model's `observation` input and of its normaliser.
    fn input_widths(blob: &WeightsBlob) -> (i64, Vec<i64>) {
        let model = ModelProto::decode(actor_model(blob).unwrap().as_slice()).unwrap();
        let graph = model.graph.unwrap();
        let shape = graph.input[0].r#type.clone().unwrap().tensor_type.unwrap().shape.unwrap();
        let mean = graph.initializer.iter().find(|t| t.name == "obs_mean").unwrap();
        (shape.dim[1].dim_value.unwrap(), mean.dims.clone())
    }

    #[test]
    fn the_model_reads_what_the_actor_reads() {
        let mut arch = Architecture { hidden: vec![8], ..Architecture::paper() };
        arch.set_observation_layout(sim::ObservationLayout { line_points: 4, ..arch.observation });
        let blob = |arch: &Architecture| pattern_blob(arch, ObsNormalizer::new(arch.observation_dim), 1, 1);
        assert_eq!(input_widths(&blob(&arch)), (52, vec![52]));
    }
}
