from neumat import report
import pandas as pd


def test_stitch_orders_sections_by_file_name_and_renders_tables(tmp_path):
    (tmp_path / "20_b.md").write_text("## Second\n\n" + report.md_table(pd.DataFrame({"x": [1.5]})))
    (tmp_path / "10_a.md").write_text("## First\n\n![fig](figures/a.png)")
    md, html = report.stitch([tmp_path / "20_b.md", tmp_path / "10_a.md"], "T", "## Config")
    assert md.index("## First") < md.index("## Second") < md.index("## Config")
    assert "<table>" in html and "<h2>First</h2>" in html
    assert '<img alt="fig" src="figures/a.png"' in html


def test_figures_get_their_captions_rendered_for_the_config(tmp_path):
    """index.md / index.html: every figure line is followed by its report() caption (a Jinja
    template over snakemake.config, RST literals as Markdown code), matched by the rule's
    output pattern; a figure without a caption is left alone."""
    cap = tmp_path / "btf.rst"
    cap.write_text("Renders at ``btf.tiling``{% if snakemake.config['x']['on'] %}, with x"
                   "{% endif %}.\nSecond line.\n")
    text = report.caption_text(cap, {"x": {"on": True}})
    assert text == "Renders at `btf.tiling`, with x. Second line."
    assert report.caption_text(cap, {"x": {"on": False}}) == "Renders at `btf.tiling`. Second line."
    (tmp_path / "60_btf.md").write_text("## BTF\n\n![wood](figures/btf_wood_tiling.png)\n\n"
                                        "![other](figures/other.png)\ntext")
    md, html = report.stitch([tmp_path / "60_btf.md"], "T",
                             captions={r"btf_[^/]+_tiling\.png": text})
    assert md.rstrip().split("\n\n")[2:5] == ["![wood](figures/btf_wood_tiling.png)", f"> {text}",
                                     "![other](figures/other.png)\ntext"]
    assert "<blockquote>\n<p>Renders at <code>btf.tiling</code>, with x." in html
