//! Procedural macros behind grainpipe's single parameter declaration.
//!
//! `#[params]` turns one struct, whose fields carry doc comments and `#[param(...)]`
//! attributes, into everything the framework needs: the serde struct (defaults filled in),
//! its `Default`, and the `Params` description that `pipe describe`, `--json`, the JSON Schema,
//! the unknown-key check and the cache read. `#[derive(ParamChoice)]` describes a unit-only
//! enum as "one of: a, b" from its serde names.

use proc_macro::TokenStream;
use proc_macro2::TokenStream as TokenStream2;
use quote::{quote, ToTokens};
use syn::{parse_macro_input, Attribute, Data, DeriveInput, Expr, Fields, ItemStruct, LitStr};

/// What `#[param(...)]` says about one field.
#[derive(Default)]
struct FieldOptions {
    default: Option<Expr>,
    ty: Option<LitStr>,
    unit: Option<LitStr>,
    reads_file: bool,
    flatten: bool,
}

fn parse_field_options(attrs: &[Attribute]) -> syn::Result<FieldOptions> {
    let mut o = FieldOptions::default();
    for a in attrs.iter().filter(|a| a.path().is_ident("param")) {
        a.parse_nested_meta(|m| {
            if m.path.is_ident("default") {
                o.default = Some(m.value()?.parse()?);
            } else if m.path.is_ident("ty") {
                o.ty = Some(m.value()?.parse()?);
            } else if m.path.is_ident("unit") {
                o.unit = Some(m.value()?.parse()?);
            } else if m.path.is_ident("file") {
                o.reads_file = true;
            } else if m.path.is_ident("flatten") {
                o.flatten = true;
            } else {
                return Err(m.error(
                    "unknown `param` option; expected default = .., ty = \"..\", unit = \"..\", file or flatten",
                ));
            }
            Ok(())
        })?;
    }
    if o.flatten && (o.ty.is_some() || o.unit.is_some() || o.reads_file) {
        return Err(syn::Error::new_spanned(
            &attrs[0],
            "a flattened parameter group takes its docs, types and units from its own \
             declaration (only `default` may be given, to set the group's defaults for this \
             stage)",
        ));
    }
    Ok(o)
}

/// The doc comment of an item, lines joined with spaces.
fn doc_text(attrs: &[Attribute]) -> String {
    let mut lines = Vec::new();
    for a in attrs {
        if !a.path().is_ident("doc") {
            continue;
        }
        if let syn::Meta::NameValue(nv) = &a.meta {
            if let Expr::Lit(syn::ExprLit {
                lit: syn::Lit::Str(s),
                ..
            }) = &nv.value
            {
                lines.push(s.value().trim().to_string());
            }
        }
    }
    lines
        .into_iter()
        .filter(|l| !l.is_empty())
        .collect::<Vec<_>>()
        .join(" ")
}

/// The name serde gives a field: its identifier, or `#[serde(rename = "..")]`.
fn serde_name(field: &syn::Field) -> syn::Result<String> {
    let mut name = field
        .ident
        .as_ref()
        .expect("named field")
        .to_string()
        .trim_start_matches("r#")
        .to_string();
    for a in field.attrs.iter().filter(|a| a.path().is_ident("serde")) {
        let _ = a.parse_nested_meta(|m| {
            if m.path.is_ident("rename") {
                let s: LitStr = m.value()?.parse()?;
                name = s.value();
            } else if let Ok(v) = m.value() {
                // Skip the value of options we do not read.
                let _: TokenStream2 = v.parse()?;
            }
            Ok(())
        });
    }
    Ok(name)
}

/// `#[params]` on a struct with named fields. Each field documents itself with a doc comment
/// and may carry `#[param(default = EXPR, ty = "words", unit = "m", file, flatten)]`:
/// - `default`: the default value (else `Default::default()` of the field's type);
/// - `ty` / `unit`: override the words and SI unit derived from the field's type;
/// - `file`: the value names an input file or directory; the cache is keyed on its content;
/// - `flatten`: the field is a parameter group (itself `#[params]`) whose keys join this one's;
///   with `default = EXPR` (a value of the group's type) this stage gets its own defaults for
///   the group's keys, and `pipe describe` shows them.
///
/// The struct gets `Clone, Debug, Serialize, Deserialize` (do not derive them again),
/// `#[serde(default)]`, a `Default` impl and `grainpipe_core::params::Params`.
#[proc_macro_attribute]
pub fn params(attr: TokenStream, item: TokenStream) -> TokenStream {
    if !attr.is_empty() {
        return syn::Error::new(
            proc_macro2::Span::call_site(),
            "`#[params]` takes no arguments",
        )
        .to_compile_error()
        .into();
    }
    let mut item = parse_macro_input!(item as ItemStruct);
    match expand_params(&mut item) {
        Ok(t) => t.into(),
        Err(e) => e.to_compile_error().into(),
    }
}

fn expand_params(item: &mut ItemStruct) -> syn::Result<TokenStream2> {
    let Fields::Named(fields) = &mut item.fields else {
        return Err(syn::Error::new_spanned(
            &item.ident,
            "`#[params]` needs a struct with named fields",
        ));
    };
    let mut defaults = Vec::new();
    let mut specs = Vec::new();
    let mut checks = Vec::new();
    for field in fields.named.iter_mut() {
        let opts = parse_field_options(&field.attrs)?;
        field.attrs.retain(|a| !a.path().is_ident("param"));
        let ident = field.ident.clone().expect("named field");
        let ty = &field.ty;
        let default = opts
            .default
            .as_ref()
            .map(|e| e.to_token_stream())
            .unwrap_or_else(|| quote!(::core::default::Default::default()));
        defaults.push(quote!(#ident: #default));
        if opts.flatten {
            field.attrs.push(syn::parse_quote!(#[serde(flatten)]));
            specs.push(quote! {
                specs.extend(<#ty as ::grainpipe_core::params::Params>::specs());
            });
            checks.push(quote! {
                if let Some(r) = <#ty as ::grainpipe_core::params::Params>::check_value(key, value) {
                    return Some(r);
                }
            });
            continue;
        }
        let doc = doc_text(&field.attrs);
        if doc.is_empty() {
            return Err(syn::Error::new_spanned(
                &ident,
                "every parameter needs a doc comment: it is what `pipe describe` shows",
            ));
        }
        let name = serde_name(field)?;
        let ty_words = match &opts.ty {
            Some(s) => quote!(::std::string::String::from(#s)),
            None => quote!(<#ty as ::grainpipe_core::params::ParamType>::type_name()),
        };
        let unit = match &opts.unit {
            Some(s) => quote!(::std::string::String::from(#s)),
            None => quote!(<#ty as ::grainpipe_core::params::ParamType>::unit().to_string()),
        };
        let reads_file = opts.reads_file;
        checks.push(quote! {
            if key == #name {
                return Some(::grainpipe_core::params::check_field::<#ty>(#name, value));
            }
        });
        specs.push(quote! {
            specs.push(::grainpipe_core::params::ParamSpec {
                name: #name,
                ty: #ty_words,
                unit: #unit,
                doc: #doc,
                reads_file: #reads_file,
                schema: <#ty as ::grainpipe_core::params::ParamType>::schema(),
                default: ::grainpipe_core::serde_json::Value::Null,
            });
        });
    }
    item.attrs.push(syn::parse_quote!(
        #[derive(Clone, Debug, ::serde::Serialize, ::serde::Deserialize)]
    ));
    item.attrs.push(syn::parse_quote!(#[serde(default)]));
    let name = &item.ident;
    let (impl_g, ty_g, where_g) = item.generics.split_for_impl();
    Ok(quote! {
        #item

        impl #impl_g ::core::default::Default for #name #ty_g #where_g {
            fn default() -> Self {
                #name { #(#defaults,)* }
            }
        }

        impl #impl_g ::grainpipe_core::params::Params for #name #ty_g #where_g {
            fn specs() -> ::std::vec::Vec<::grainpipe_core::params::ParamSpec> {
                let mut specs = ::std::vec::Vec::new();
                #(#specs)*
                ::grainpipe_core::params::fill_defaults(&mut specs, &Self::default());
                specs
            }

            fn check_value(
                key: &str,
                value: &::grainpipe_core::serde_json::Value,
            ) -> ::core::option::Option<::core::result::Result<(), (::std::string::String, ::std::string::String)>> {
                #(#checks)*
                None
            }
        }
    })
}

/// Describes a unit-only enum as a parameter type: "one of: a, b" from its serde names,
/// with each variant's doc comment for `pipe describe`.
#[proc_macro_derive(ParamChoice)]
pub fn param_choice(item: TokenStream) -> TokenStream {
    let input = parse_macro_input!(item as DeriveInput);
    match expand_choice(&input) {
        Ok(t) => t.into(),
        Err(e) => e.to_compile_error().into(),
    }
}

fn expand_choice(input: &DeriveInput) -> syn::Result<TokenStream2> {
    let Data::Enum(e) = &input.data else {
        return Err(syn::Error::new_spanned(
            &input.ident,
            "`ParamChoice` is for enums whose variants carry no data",
        ));
    };
    let name = &input.ident;
    let mut variants = Vec::new();
    let mut docs = Vec::new();
    for v in &e.variants {
        if !matches!(v.fields, Fields::Unit) {
            return Err(syn::Error::new_spanned(
                v,
                "`ParamChoice` variants carry no data; implement `ParamType` by hand for this enum",
            ));
        }
        let ident = &v.ident;
        variants.push(quote!(#name::#ident));
        docs.push(doc_text(&v.attrs));
    }
    Ok(quote! {
        impl ::grainpipe_core::params::ParamType for #name {
            fn type_name() -> ::std::string::String {
                ::grainpipe_core::params::choice_type_name(&Self::choices())
            }
            fn schema() -> ::grainpipe_core::serde_json::Value {
                ::grainpipe_core::params::choice_schema(&Self::choices())
            }
        }
        impl #name {
            /// The YAML spelling of every variant, with its doc comment.
            pub fn choices() -> ::std::vec::Vec<(::std::string::String, &'static str)> {
                let variants = [#(#variants),*];
                let docs: ::std::vec::Vec<&'static str> = ::std::vec![#(#docs),*];
                variants
                    .iter()
                    .zip(docs)
                    .map(|(v, d)| (::grainpipe_core::params::serde_word(v), d))
                    .collect()
            }
        }
    })
}
