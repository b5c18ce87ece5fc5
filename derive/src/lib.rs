//! `#[derive(pulicast::Schema)]`, so that a message type needs only
//! `pulicast` and `serde` among its crate's dependencies.
//!
//! `postcard-schema`'s own derive names its crate as `::postcard_schema`,
//! which resolves only where that crate is a direct dependency. This derive
//! hands the type to it anyway, through the copy that `pulicast`
//! re-exports: it declares a private twin of the type (same fields, same
//! `serde` and `postcard` attributes, renamed for serde to the type's own
//! name, so the schema and its fingerprint are the same), derives the
//! schema of the twin with `#[postcard(crate = ...)]` pointing into
//! `pulicast`, and gives the type the twin's schema. Nothing of the schema
//! logic is written here.

use proc_macro::TokenStream;
use proc_macro2::TokenStream as TokenStream2;
use quote::{format_ident, quote};
use syn::{parse_macro_input, parse_quote, Attribute, Data, DeriveInput, Fields};

/// Derives `pulicast::Schema` (postcard-schema's `Schema` trait) for a
/// struct or enum, as `#[derive(postcard_schema::Schema)]` would, without a
/// dependency on `postcard-schema`. Takes the same `#[postcard(...)]` and
/// `#[serde(rename = ...)]` attributes.
#[proc_macro_derive(Schema, attributes(postcard, serde))]
pub fn derive_schema(input: TokenStream) -> TokenStream {
    let input = parse_macro_input!(input as DeriveInput);
    expand(input)
        .unwrap_or_else(syn::Error::into_compile_error)
        .into()
}

/// Keeps only the attributes postcard-schema's derive reads.
fn keep_schema_attributes(attrs: &mut Vec<Attribute>) {
    attrs.retain(|a| a.path().is_ident("serde") || a.path().is_ident("postcard"));
}

fn keep_in_fields(fields: &mut Fields) {
    for field in fields.iter_mut() {
        keep_schema_attributes(&mut field.attrs);
        field.vis = syn::Visibility::Inherited;
    }
}

/// The schema's name for the type, read as postcard-schema's derive reads
/// it: the first `rename = "..."` of a `#[serde(...)]` attribute, looked
/// for up to the first setting with a value that is not `rename` (where
/// that derive stops reading the attribute), else the type's own name.
fn schema_name(input: &DeriveInput) -> String {
    let mut rename = None;
    for attr in input.attrs.iter().filter(|a| a.path().is_ident("serde")) {
        let _: syn::Result<()> = attr.parse_nested_meta(|meta| {
            if meta.path.is_ident("rename") {
                rename = Some(meta.value()?.parse::<syn::LitStr>()?.value());
            }
            Ok(())
        });
    }
    rename.unwrap_or_else(|| input.ident.to_string())
}

fn expand(input: DeriveInput) -> syn::Result<TokenStream2> {
    let name = &input.ident;
    let mut twin = input.clone();
    twin.ident = format_ident!("__PulicastSchemaTwinOf{}", name);
    twin.vis = syn::Visibility::Inherited;
    // The twin's only serde attribute on the container is the name the
    // schema gets; its postcard attributes (bound, crate) stay.
    twin.attrs.retain(|a| a.path().is_ident("postcard"));
    let schema_name = schema_name(&input);
    twin.attrs
        .push(parse_quote!(#[serde(rename = #schema_name)]));
    match &mut twin.data {
        Data::Struct(s) => keep_in_fields(&mut s.fields),
        Data::Enum(e) => {
            for variant in &mut e.variants {
                keep_schema_attributes(&mut variant.attrs);
                keep_in_fields(&mut variant.fields);
                // Values need the type's `repr`, which the twin has not;
                // schemas don't carry them.
                variant.discriminant = None;
            }
        }
        Data::Union(u) => {
            return Err(syn::Error::new(
                u.union_token.span,
                "pulicast::Schema can't be derived for a union",
            ))
        }
    }
    let twin_name = &twin.ident;
    let (impl_generics, ty_generics, where_clause) = input.generics.split_for_impl();
    let mut where_clause = where_clause.cloned().unwrap_or_else(|| parse_quote!(where));
    where_clause.predicates.push(
        parse_quote!(#twin_name #ty_generics: ::pulicast::__private::postcard_schema::Schema),
    );
    Ok(quote! {
        const _: () = {
            #[derive(::pulicast::__private::postcard_schema::Schema)]
            #[postcard(crate = ::pulicast::__private::postcard_schema)]
            #[allow(dead_code, non_camel_case_types, clippy::all)]
            #twin

            #[allow(private_bounds)]
            impl #impl_generics ::pulicast::__private::postcard_schema::Schema for #name #ty_generics
            #where_clause
            {
                const SCHEMA: &'static ::pulicast::__private::postcard_schema::schema::NamedType =
                    <#twin_name #ty_generics as ::pulicast::__private::postcard_schema::Schema>::SCHEMA;
            }
        };
    })
}
