# Preprocessing made visible: the filtered channels and the model input that
# identification and discovery compare (they filter the raw campaign themselves,
# with the same τ, so this step is for inspection and feeds no other rule), a
# sensor-noise table and a raw-vs-filtered figure. `mbst preprocess` writes into
# a temporary folder that replaces results/{campaign}/preprocess whole.


rule preprocess:
    input:
        campaign_inputs,
    output:
        campaign=directory("results/{campaign}/preprocess/campaign"),
        noise="results/{campaign}/preprocess/preprocess.md",
        noise_html=report(
            "results/{campaign}/preprocess/preprocess.html",
            caption="../report/preprocess_md.rst",
            category="Preprocessing",
            subcategory="{campaign}",
            labels={"campaign": "{campaign}", "result": "noise table"},
        ),
        figure=report(
            "results/{campaign}/preprocess/figures/filter.png",
            caption="../report/preprocess_figure.rst",
            category="Preprocessing",
            subcategory="{campaign}",
            labels={"campaign": "{campaign}", "result": "figure: raw vs filtered"},
        ),
    log:
        "logs/preprocess/{campaign}.log",
    params:
        campaign_dir=campaign_dir,
        outdir=lambda wildcards, output: os.path.dirname(output.noise),
        tau_s=config["preprocess"]["tau_s"],
        code=CODE_VERSION,
    conda:
        "../envs/mbst.yaml"
    shell:
        "mbst preprocess {params.campaign_dir:q} --out {params.outdir:q}"
        " --tau {params.tau_s} --quiet > {log:q} 2>&1"
